"""A convolution of a channel concatenation, run part by part (what exported graphs run).

``conv(cat(parts, 1))`` equals the sum over parts of the convolution of each part with its slice
of the input channels of the weights (a convolution is linear in its input channels), plus the
bias once. An exported graph then has no full-resolution concatenation and no reorder of it into
the convolution's layout; the numbers are the same up to float rounding of the sum's order.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn


def conv_of_parts(conv: nn.Conv2d, parts: Sequence[torch.Tensor]) -> torch.Tensor:
    """``conv(torch.cat(parts, 1))`` without the concatenation.

    conv: a ``Conv2d`` with ``in_channels == sum C_i``; parts: ``[B, C_i, H, W]`` in the
    concatenation's order -> ``[B, conv.out_channels, H', W']``.
    """
    out, start = None, 0
    for part in parts:
        n = part.shape[1]
        y = F.conv2d(part, conv.weight[:, start: start + n], None, conv.stride, conv.padding,
                     conv.dilation, conv.groups)
        out, start = (y if out is None else out + y), start + n
    return out if conv.bias is None else out + conv.bias.view(1, -1, 1, 1)
