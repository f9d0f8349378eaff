"""PatchCritic: a small convolutional patch discriminator for adversarial distillation.

A stack of stride-2 4x4 convolutions with LeakyReLU (no normalisation layers, so the critic's
output for one patch does not depend on the rest of the batch), ending in a 3x3 convolution to
one logit per patch. With ``widths = [w_1, ..., w_n]`` the receptive field of one logit is
about ``2^(n+1) + 2^n`` pixels and the output is ``[B, 1, H / 2^n, W / 2^n]`` (floor for sizes
that are not multiples). Spectral normalisation (``spectral_norm=True``) bounds each layer's
Lipschitz constant, which keeps adversarial training stable.

The critic reads whatever image representation the training module gives it; feed it bounded
values (e.g. the tonemapped frame or ``log1p`` radiance), not raw HDR.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm as _spectral_norm


class PatchCritic(nn.Module):
    """Patch discriminator.

    Args:
        in_channels: channels of the judged image (3; 6 to also condition on e.g. the noisy input).
        widths: channels of the stride-2 layers.
        spectral_norm: wrap every convolution in spectral normalisation.
        negative_slope: LeakyReLU slope.
    """

    def __init__(self, in_channels: int = 3, widths: Sequence[int] = (32, 64, 128),
                 spectral_norm: bool = True, negative_slope: float = 0.2):
        super().__init__()
        wrap = _spectral_norm if spectral_norm else (lambda m: m)
        layers: list[nn.Module] = []
        cin = in_channels
        for width in widths:
            layers += [wrap(nn.Conv2d(cin, width, 4, stride=2, padding=1)), nn.LeakyReLU(negative_slope)]
            cin = width
        layers.append(wrap(nn.Conv2d(cin, 1, 3, padding=1)))
        self.layers = nn.Sequential(*layers)
        self.downsampling = 2 ** len(widths)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: ``[B, in_channels, H, W]`` (H, W >= 2^len(widths)) -> logits ``[B, 1, H/2^n, W/2^n]``."""
        return self.layers(x)
