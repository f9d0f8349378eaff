"""U-Net with one 1x1 output head per pyramid level (docs/design.md §2, "How the U-Net reads").

With ``encoder = [e0, e1, ..., e_{n-1}]``, ``bottleneck = b`` and ``decoder = [d0, ..., d_{n-2}]``:

* encoder block i runs at scale 1/2^i: ``conv3x3(e_i) LReLU conv3x3(e_i) LReLU``, its output is
  kept as skip i, then a 2x2 max-pool;
* the bottleneck runs at 1/2^n: two conv3x3 of width b, then a 2x upsample;
* decoder block j runs at scale 1/2^(n-1-j): concatenate skip (n-1-j) with the upsampled input,
  two conv3x3 of width d_j, then a 2x upsample;
* at full resolution the upsampled features are concatenated with skip 0: that concatenation
  feeds the level-0 head.

The level-i head (a 1x1 conv) reads the features at scale 1/2^i: level 0 the full-resolution
concatenation, level i >= 1 the output of the decoder block at scale 1/2^i (before its
upsample). These n maps are also returned as ``features`` (for feature distillation);
``feature_channels`` lists their widths. Input height and width must be multiples of 2^n
(:class:`~denoiser.nn.denoiser.Denoiser` pads).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.errors import ConfigError
from denoiser.nn.graph_mode import fused_kernels, in_graph, matmul_heads
from denoiser.nn.graph_ops import graph_node
from denoiser.nn.parts import conv_of_parts, pointwise, pointwise_of_parts


def conv_block(cin: int, cout: int, negative_slope: float) -> nn.Sequential:
    """``conv3x3 LReLU conv3x3 LReLU``: ``[B, cin, H, W] -> [B, cout, H, W]``."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.LeakyReLU(negative_slope, inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.LeakyReLU(negative_slope, inplace=True),
    )


class UNet(nn.Module):
    """U-Net with per-level output heads.

    Args:
        in_channels: input channels (set by :class:`Denoiser`).
        encoder: widths of the encoder blocks, finest first (student ``[32, 64, 128]``).
        bottleneck: width of the bottleneck at 1/2^len(encoder) (student 128).
        decoder: widths of the decoder blocks, coarsest first (student ``[64, 32]``);
            ``len(decoder) == len(encoder) - 1``.
        head_channels: output channels per level, finest first (0 = no head at that level);
            at most ``len(encoder)`` levels.
        negative_slope: LeakyReLU slope.
        upsample: ``F.interpolate`` mode of the 2x upsampling ("bilinear" or "nearest").
    """

    def __init__(self, in_channels: int, encoder: Sequence[int], bottleneck: int,
                 decoder: Sequence[int], head_channels: Sequence[int],
                 negative_slope: float = 0.1, upsample: str = "bilinear"):
        super().__init__()
        encoder, decoder, head_channels = list(encoder), list(decoder), list(head_channels)
        if len(encoder) < 1:
            raise ConfigError("net.unet.encoder: needs at least one width")
        if len(decoder) != len(encoder) - 1:
            raise ConfigError(
                f"net.unet.decoder: expected {len(encoder) - 1} widths for {len(encoder)} encoder "
                f"blocks, got {len(decoder)}")
        if len(head_channels) > len(encoder):
            raise ConfigError(
                f"kernel.sizes: {len(head_channels)} pyramid levels need a U-Net with at least as "
                f"many scales, net.unet.encoder has {len(encoder)}")
        self.levels = len(encoder)
        self.multiple = 2 ** self.levels
        self.upsample_mode = upsample
        self.align = False if upsample in ("bilinear", "bicubic") else None

        self.encoder = nn.ModuleList()
        cin = in_channels
        for width in encoder:
            self.encoder.append(conv_block(cin, width, negative_slope))
            cin = width
        self.bottleneck = conv_block(cin, bottleneck, negative_slope)
        self.decoder = nn.ModuleList()
        cin = bottleneck
        for j, width in enumerate(decoder):
            skip = encoder[self.levels - 1 - j]
            self.decoder.append(conv_block(cin + skip, width, negative_slope))
            cin = width
        # features per level, finest first
        self.feature_channels = [encoder[0] + cin] + [decoder[self.levels - 1 - i]
                                                      for i in range(1, self.levels)]
        self.heads = nn.ModuleList(
            [nn.Conv2d(self.feature_channels[i], n, 1) if n > 0 else nn.Identity()
             for i, n in enumerate(head_channels)])
        self.head_channels = head_channels

    def _up(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, scale_factor=2, mode=self.upsample_mode, align_corners=self.align)

    def first_conv_of_parts(self, parts: Sequence[torch.Tensor]) -> torch.Tensor:
        """The first convolution of ``torch.cat(parts, 1)`` without the concatenation: a sum of
        one convolution per part with its slice of the weights (convolution is linear in its
        input channels). parts: ``[B, C_i, H, W]`` with ``sum C_i == in_channels`` ->
        ``[B, encoder[0], H, W]`` (before its LeakyReLU). Same numbers up to float rounding
        of the sum's order; what the exported graph runs (no full-resolution concatenation
        and layout reorder of the U-Net input)."""
        return conv_of_parts(self.encoder[0][0], parts)

    def forward(self, x: torch.Tensor | Sequence[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """x: ``[B, C_in, H, W]`` with H, W multiples of ``self.multiple``, or a list of parts
        whose channel concatenation is that input (:meth:`first_conv_of_parts`).

        Returns ``(heads, features)``: ``heads[i]``: ``[B, head_channels[i], H/2^i, W/2^i]``
        (None where head_channels[i] == 0; heads[0] a :class:`FactoredHead` in a graph exported
        with matmul heads and the fused operations: read it through :func:`head_channels`); ``features[i]``: ``[B, feature_channels[i], H/2^i,
        W/2^i]`` for i in 0..levels-1.
        """
        skips = []
        for i, block in enumerate(self.encoder):
            if i == 0 and not isinstance(x, torch.Tensor):
                x = block[1:](self.first_conv_of_parts(x))
            else:
                x = block(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        half = self.bottleneck(x)  # the input of the last 2x upsampling, at 1/2 resolution
        x = self._up(half)
        features: list[torch.Tensor] = [None] * self.levels  # type: ignore[list-item]
        # exported for OpenVINO f32 (matmul_heads): each decoder block's first convolution per
        # part (the skip and the upsampled features), without their concatenation (conv_of_parts)
        decoder_parts = matmul_heads() and in_graph()
        for j, block in enumerate(self.decoder):
            scale = self.levels - 1 - j
            if decoder_parts:
                x = block[1:](conv_of_parts(block[0], [skips[scale], x]))
            else:
                x = block(torch.cat([skips[scale], x], dim=1))
            features[scale] = x
            half, x = x, self._up(x)
        features[0] = torch.cat([skips[0], x], dim=1)
        # exported for OpenVINO f32 (matmul_heads): each head as matrix products, the level-0 head
        # per part (skip 0 and the upsampled features, no concatenation); see pointwise_of_parts
        as_matmul = matmul_heads() and in_graph()
        parts = [[skips[0], x]] + [[f] for f in features[1:]]
        heads = [(pointwise_of_parts(head, parts[i]) if as_matmul else head(features[i])) if n > 0 else None
                 for i, (head, n) in enumerate(zip(self.heads, self.head_channels))]
        if as_matmul and fused_kernels() and self.head_channels[0] > 0:
            heads[0] = self.head0_before_upsampling(skips[0], half)
        return heads, features

    def head0_before_upsampling(self, skip0: torch.Tensor, half: torch.Tensor) -> FactoredHead:
        """The level-0 head of ``[skip0, up(half)]`` as its factors (:class:`FactoredHead`), with
        its upsampled part's product taken at half resolution. skip0: ``[B, C_0, H, W]``; half:
        ``[B, C_u, H/2, W/2]``; its :meth:`FactoredHead.tensor` is ``[B, head_channels[0], H,
        W]``."""
        head = self.heads[0]
        return FactoredHead(skip0, half, head.weight[:, :, 0, 0], head.bias, self.upsample_mode, self.align)


@dataclass(frozen=True)
class FactoredHead:
    """A level-0 head ``W_s skip0 + up(W_u half + b)`` kept as its factors: the 1x1 convolution of
    ``[skip0, up(half)]`` with the upsampled part's product taken at half resolution (a 1x1
    convolution and the 2x upsampling, bilinear or nearest with weights summing to 1, are linear
    maps over channels and over pixels respectively, so they commute: the same numbers up to
    float rounding, with a quarter of that part's multiply-adds; the bias joins the
    half-resolution product). What a graph exported with matmul heads and the fused operations
    (:func:`~denoiser.nn.graph_mode.kernels_as_op`) carries as ``heads[0]``: the pyramid filter
    computes the rows of its channels where it reads them (``denoiser::PyramidFilterHead``), so
    the full-resolution head is never written; other readers take :meth:`tensor`.

    skip0: ``[B, C_0, H, W]``; half: ``[B, C_u, H/2, W/2]``; weight: ``[C_out, C_0 + C_u]``; bias:
    ``[C_out]`` or None; mode, align: the upsampling's (``F.interpolate``).
    """

    skip0: torch.Tensor
    half: torch.Tensor
    weight: torch.Tensor
    bias: torch.Tensor | None
    mode: str
    align: bool | None

    def select(self, start: int, stop: int | None = None) -> FactoredHead:
        """Output channels ``start:stop`` (as ``head[:, start:stop]``)."""
        bias = None if self.bias is None else self.bias[start:stop]
        return FactoredHead(self.skip0, self.half, self.weight[start:stop], bias, self.mode, self.align)

    @property
    def skip_weight(self) -> torch.Tensor:
        """``W_s``: ``[C_out, C_0]``."""
        return self.weight[:, : self.skip0.shape[1]]

    def upsampled_part(self) -> torch.Tensor:
        """``W_u half + b`` before its upsampling: ``[B, C_out, H/2, W/2]``."""
        return pointwise(self.weight[:, self.skip0.shape[1]:], self.bias, self.half)

    def tensor(self) -> torch.Tensor:
        """The head ``[B, C_out, H, W]``: in the f32 graph with the fused operations one
        ``denoiser::FactoredHead`` node (skip0 read channels-last, the product and the upsampled
        part's sum row by row, written planar: no full-resolution product written and read again;
        with OpenVINO's own upsampling its channels-last output made the head's channel split a
        137 ms reference node at 1080p)."""
        z = self.upsampled_part()
        if fused_kernels():
            return FactoredHeadOp.apply(self.skip0.permute(0, 2, 3, 1), self.skip_weight, z, self.mode, self.align)
        a = pointwise(self.skip_weight, None, self.skip0)
        return a + F.interpolate(z, size=a.shape[-2:], mode=self.mode, align_corners=self.align)


def head_channels(head: torch.Tensor | FactoredHead, start: int, stop: int | None = None,
                  factored: bool = False) -> torch.Tensor | FactoredHead:
    """Channels ``start:stop`` of a head ``[B, C, H, W]`` or :class:`FactoredHead`: a tensor, or with
    ``factored`` a factored head stays one (for a filter that reads it: ``PyramidFilter``)."""
    if isinstance(head, FactoredHead):
        head = head.select(start, stop)
        return head if factored else head.tensor()
    return head[:, start:stop]


# ----------------------------------------------------------------------------- export stub


class FactoredHeadOp(torch.autograd.Function):
    """:meth:`denoiser.nn.unet.FactoredHead.tensor` recorded as one ``denoiser::FactoredHead`` node
    (attribute ``mode``): forward(skip ``[B, H, W, C_s]`` channels-last, weight ``[C, C_s]``, z
    ``[B, C, h, w]``, mode, align) -> ``[B, C, H, W]`` float32, ``weight @ skip +
    interpolate(z)`` (the value: the plain computation)."""

    @staticmethod
    def forward(ctx, skip, weight, z, mode, align):
        a = pointwise(weight, None, skip.permute(0, 3, 1, 2))
        return a + F.interpolate(z, size=a.shape[-2:], mode=mode, align_corners=align)

    @staticmethod
    def symbolic(g, skip, weight, z, mode, align):
        out = graph_node(g, "FactoredHead", skip, weight, z, like=z, mode=mode)
        s, zs = skip.type().varyingSizes(), z.type().varyingSizes()  # [B, H, W, C_s], [B, C, h, w]
        if s is not None and zs is not None and len(s) == 4 and len(zs) == 4:
            out.setType(z.type().with_sizes([s[0], zs[1], s[1], s[2]]))
        return out
