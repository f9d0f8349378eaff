"""EmbedNet: three 1x1 convolutions with LeakyReLU, per sample or per pixel.

With per-sample radiance available the same three layers run on every sample's features
(its own color feature next to the frame's guide features) and the results are averaged over
the samples; otherwise they run once per pixel on the mean color. Both paths share weights,
so a network trained with samples also runs on frames without them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.buffers import CHANNELS
from denoiser.nn.graph_mode import fused_kernels, matmul_heads
from denoiser.nn.graph_ops import graph_node
from denoiser.nn.inputs import color_feature
from denoiser.nn.parts import conv_of_parts


class EmbedNet(nn.Module):
    """Three 1x1 conv layers, each followed by LeakyReLU.

    Args:
        in_channels: input feature channels per sample / pixel (set by :class:`Denoiser`).
        hidden: width of the two hidden layers (docs/design.md §2: student 32, teacher 256).
        out_channels: output width (defaults to ``hidden``).
        negative_slope: LeakyReLU slope.
    """

    def __init__(self, in_channels: int, hidden: int, out_channels: int | None = None,
                 negative_slope: float = 0.1):
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels or hidden
        self.layers = nn.Sequential(
            nn.Conv2d(in_channels, hidden, 1),
            nn.LeakyReLU(negative_slope, inplace=True),
            nn.Conv2d(hidden, hidden, 1),
            nn.LeakyReLU(negative_slope, inplace=True),
            nn.Conv2d(hidden, self.out_channels, 1),
            nn.LeakyReLU(negative_slope, inplace=True),
        )

    def forward(self, x: torch.Tensor | Sequence[torch.Tensor], color_scale: torch.Tensor | None = None) -> torch.Tensor:
        """Per-pixel path ``x: [B, C_in, H, W]`` or per-sample path ``x: [B, S, C_in, H, W]``,
        or the per-pixel input as a list of parts ``[B, C_i, H, W]`` whose channel concatenation
        it is (``sum C_i == C_in``): the first layer then runs per part with its slice of the
        weights and the results are summed (what the exported graph runs: no full-resolution
        concatenation of the inputs; the same numbers up to float rounding of the sum). In the
        f32 graph with the fused operations (:func:`~denoiser.nn.graph_mode.matmul_heads` and
        :func:`~denoiser.nn.graph_mode.fused_kernels`) the three layers are one
        ``denoiser::EmbedNet`` node. color_scale (parts only): ``[B, 1, 1, 1]``: the first part is
        the linear colour buffer ``[B, 3, H, W]`` float32, whose :func:`~denoiser.nn.inputs.color_feature`
        with this scale is the input (taken inside that node in the f32 graph).

        Returns ``[B, C_out, H, W]`` (for samples: the mean over S of the per-sample output).
        """
        if not isinstance(x, torch.Tensor):
            x = list(x)
            if fused_kernels() and matmul_heads():  # the f32 graph: one denoiser::EmbedNet node
                convs = [self.layers[i] for i in (0, 2, 4)]
                weights = [t for conv in convs for t in (conv.weight[:, :, 0, 0], conv.bias)]
                color = 0 if color_scale is None else CHANNELS["color"]  # the first part: the colour
                scale = torch.ones_like(x[0][:, :1, :1, :1]) if color_scale is None else color_scale
                return EmbedNetOp.apply(self.layers[1].negative_slope, color, *weights, scale, *x).permute(0, 3, 1, 2)
            if color_scale is not None:
                x[0] = color_feature(x[0], color_scale).to(self.layers[0].weight.dtype)
            return self.layers[1:](conv_of_parts(self.layers[0], x))
        if x.dim() == 5:
            b, s, c, h, w = x.shape
            y = self.layers(x.reshape(b * s, c, h, w))
            return y.reshape(b, s, self.out_channels, h, w).mean(dim=1)
        return self.layers(x)


# ----------------------------------------------------------------------------- export stub


class EmbedNetOp(torch.autograd.Function):
    """:class:`denoiser.nn.embed.EmbedNet`'s per-pixel path on a list of input parts, recorded as one
    ``denoiser::EmbedNet`` node (attributes ``negative_slope``, ``color_channels``): the three 1x1
    layers per pixel, the hidden values never written at full resolution.

    forward(negative_slope, color_channels, w0 ``[M, C]``, b0 ``[M]``, w1 ``[M, M]``, b1, w2 ``[N,
    M]``, b2 ``[N]``, scale ``[B, 1, 1, 1]``, *parts ``[B, C_i, H, W]`` with ``sum C_i == C``) ->
    ``[B, H, W, N]`` float32, channels-last (the layout the U-Net's first convolution reads; the
    caller permutes it to ``[B, N, H, W]``). The first ``color_channels`` input channels are
    linear colour: the node takes their :func:`denoiser.nn.inputs.color_feature` with ``scale``
    first (0: none, ``scale`` unread).
    """

    @staticmethod
    def forward(ctx, negative_slope, color_channels, w0, b0, w1, b1, w2, b2, scale, *parts):
        x = torch.cat(parts, 1)
        if color_channels:
            x = torch.cat([torch.log1p(x[:, :color_channels].clamp_min(0) / scale), x[:, color_channels:]], 1)
        x = x.permute(0, 2, 3, 1)
        for w, b in ((w0, b0), (w1, b1), (w2, b2)):
            x = F.leaky_relu(x @ w.t() + b, negative_slope)
        return x.contiguous()

    @staticmethod
    def symbolic(g, negative_slope, color_channels, w0, b0, w1, b1, w2, b2, scale, *parts):
        out = graph_node(g, "EmbedNet", w0, b0, w1, b1, w2, b2, scale, *parts, like=parts[0],
                         negative_slope=float(negative_slope), color_channels=int(color_channels))
        sizes = parts[0].type().varyingSizes()  # [B, H, W, N] (None where not known)
        n = w2.type().varyingSizes()
        if sizes is not None and len(sizes) == 4 and n is not None:
            out.setType(parts[0].type().with_sizes([sizes[0], sizes[2], sizes[3], n[0]]))
        return out
