"""A convolution of a channel concatenation, run part by part (what exported graphs run).

``conv(cat(parts, 1))`` equals the sum over parts of the convolution of each part with its slice
of the input channels of the weights (a convolution is linear in its input channels), plus the
bias once. An exported graph then has no full-resolution concatenation and no reorder of it into
the convolution's layout; the numbers are the same up to float rounding of the sum's order.

:func:`pointwise_of_parts` does the same for a 1x1 convolution, as matrix products over the
channels-last view of each part: what the exported graph runs for the U-Net's heads (see there).
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


def pointwise_of_parts(conv: nn.Conv2d, parts: Sequence[torch.Tensor]) -> torch.Tensor:
    """A 1x1 ``conv(torch.cat(parts, 1))`` as one matrix product per part, ``W_i @ X_i^T`` with
    ``X_i`` the part's channels-last rows ``[B, H*W, C_i]``.

    conv: a 1x1 ``Conv2d`` (stride 1, no groups) with ``in_channels == sum C_i``; parts:
    ``[B, C_i, H, W]`` in the concatenation's order -> ``[B, conv.out_channels, H, W]``. Same
    multiply-adds and the same numbers up to float rounding.

    Why (exported graphs): OpenVINO keeps a convolution's output channels-last; a 1x1 head
    feeding a softmax over channels or a channel split (planar there) got a slow reference
    reorder in float32 (124 ms for the paper student's 38-channel level-0 head at 1080p on 2
    threads, plus reference splits). Written as ``W @ X^T`` over the channels-last rows (the
    transposes are spelled out so that the engine reads the producer's channels-last memory as
    the transposed operand), the product lands in planar order directly: no reorder and no
    transpose node (docs/export.md).
    """
    weight = conv.weight[:, :, 0, 0]  # [C_out, C_in]
    b, _, h, w = parts[0].shape
    out, start = None, 0
    for part in parts:
        n = part.shape[1]
        y = _product(weight[:, start: start + n], part)
        out, start = (y if out is None else out + y), start + n
    if conv.bias is not None:
        out = out + conv.bias.view(1, -1, 1)
    return out.reshape(b, -1, h, w)


def _product(weight: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``W @ X^T`` over the channels-last rows of x: weight ``[C_out, C_in]``, x ``[B, C_in, H, W]``
    -> ``[B, C_out, H*W]`` (see :func:`pointwise_of_parts` for why this form)."""
    return torch.matmul(weight, x.permute(0, 2, 3, 1).flatten(1, 2).transpose(1, 2))


def pointwise(weight: torch.Tensor, bias: torch.Tensor | None, x: torch.Tensor) -> torch.Tensor:
    """A 1x1 convolution as the matrix product of :func:`pointwise_of_parts` (one part):
    weight ``[C_out, C_in]``, bias ``[C_out]`` or None, x ``[B, C_in, H, W]`` -> ``[B, C_out, H, W]``."""
    b, _, h, w = x.shape
    out = _product(weight, x)
    if bias is not None:
        out = out + bias.view(1, -1, 1)
    return out.reshape(b, -1, h, w)


