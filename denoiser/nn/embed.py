"""EmbedNet: three 1x1 convolutions with LeakyReLU, per sample or per pixel.

With per-sample radiance available the same three layers run on every sample's features
(its own color feature next to the frame's guide features) and the results are averaged over
the samples; otherwise they run once per pixel on the mean color. Both paths share weights,
so a network trained with samples also runs on frames without them.
"""

from __future__ import annotations

import torch
from torch import nn


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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Per-pixel path ``x: [B, C_in, H, W]`` or per-sample path ``x: [B, S, C_in, H, W]``.

        Returns ``[B, C_out, H, W]`` (for samples: the mean over S of the per-sample output).
        """
        if x.dim() == 5:
            b, s, c, h, w = x.shape
            y = self.layers(x.reshape(b * s, c, h, w))
            return y.reshape(b, s, self.out_channels, h, w).mean(dim=1)
        return self.layers(x)
