"""Backward warping with motion vectors (docs/design.md §3.1 convention).

The surface seen at pixel centre ``p`` in frame t was at ``p + motion(p)`` in frame t-1
(pixels; x to the right, y downward). ``warp_to_current`` therefore samples the previous
frame's buffer at ``p + motion(p)`` with bilinear ``grid_sample`` and zeros outside the image.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from denoiser.nn.graph_mode import untraced
from denoiser.nn.graph_ops import graph_node
from denoiser.nn.inputs import sanitize
from denoiser.nonfinite import POSINF

#: motion is clamped to +-(MOTION_LIMIT * max(H, W)) pixels: anything beyond is off-screen
#: anyway, and the clamp keeps grid coordinates small and finite.
MOTION_LIMIT = 4.0

#: sample position (pixels) of a discarded history item: off the image by more than the
#: bilinear footprint, so nothing is read there
OUTSIDE = -2.0


def sample_positions(motion: torch.Tensor, keep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pixel samples the previous frame, in pixels: ``(x [B, 1, H, W], y [B, 1, H, W])``
    float32, ``p + motion(p)`` (motion: ``[B, 2, H, W]``; NaN, -Inf -> 0, +Inf -> 65504; clamped
    to ``MOTION_LIMIT`` frame sizes). keep: bool ``[B, 1, 1, 1]`` or None; where False, every
    position is moved to ``OUTSIDE`` (off the image, so that item samples nothing: zeros and
    coverage 0, whatever the previous buffers hold, NaN included)."""
    h, w = motion.shape[-2:]
    limit = MOTION_LIMIT * max(h, w)
    m = sanitize(motion).clamp(-limit, limit)
    ys = torch.arange(h, device=motion.device, dtype=torch.float32).view(1, 1, h, 1)
    xs = torch.arange(w, device=motion.device, dtype=torch.float32).view(1, 1, 1, w)
    sx, sy = xs + m[:, 0:1], ys + m[:, 1:2]
    if keep is not None:
        sx = torch.where(keep, sx, OUTSIDE)
    return sx, sy


def grid_from_positions(sx: torch.Tensor, sy: torch.Tensor) -> torch.Tensor:
    """``grid_sample`` grid ``[B, H, W, 2]`` (``align_corners=False``) of pixel positions
    ``[B, 1, H, W]`` (:func:`sample_positions`): ``g = (s + 0.5) * 2 / size - 1``."""
    h, w = sx.shape[-2:]
    gx = (sx + 0.5) * (2.0 / w) - 1.0
    gy = (sy + 0.5) * (2.0 / h) - 1.0
    # [B, 2, H, W] then one transpose to [B, H, W, 2]: stacking x and y along a new last axis
    # is an interleaving copy that inference engines run slowly (OpenVINO: a reference Concat)
    return torch.cat([gx, gy], dim=1).permute(0, 2, 3, 1)


def sampling_grid(motion: torch.Tensor) -> torch.Tensor:
    """Normalised ``grid_sample`` grid for backward motion.

    motion: ``[B, 2, H, W]`` pixels (x right, y down; NaN, -Inf -> 0, +Inf -> 65504) -> ``[B, H, W, 2]`` float32 in
    ``align_corners=False`` convention: ``g = (p + motion + 0.5) * 2 / size - 1``.
    """
    return grid_from_positions(*sample_positions(motion))


def _axis_coverage(s: torch.Tensor, size: int) -> torch.Tensor:
    """Weight of the in-image taps of 1-D linear interpolation at position ``s`` (any shape)
    on ``size`` samples: ``(1 - f) [0 <= i < size] + f [0 <= i + 1 < size]``, ``i = floor(s)``."""
    i = torch.floor(s)
    f = s - i
    return (torch.where((i >= 0) & (i <= size - 1), 1.0 - f, 0.0)
            + torch.where((i >= -1) & (i <= size - 2), f, 0.0))


def coverage(sx: torch.Tensor, sy: torch.Tensor) -> torch.Tensor:
    """Fraction of the bilinear footprint at positions ``[B, 1, H, W]`` (:func:`sample_positions`)
    that lies inside the image: ``[B, 1, H, W]`` in [0, 1], what warping a constant image of ones
    gives (bilinear weights are separable), computed per pixel without sampling anything."""
    h, w = sx.shape[-2:]
    return _axis_coverage(sx, w) * _axis_coverage(sy, h)


def warp_to_current(x: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Warp the previous frame's buffer to the current frame.

    x: ``[B, C, H, W]`` buffer of frame t-1; motion: ``[B, 2, H, W]`` backward motion of frame t.
    Returns ``[B, C, H, W]`` float32: ``x`` sampled bilinearly at ``p + motion(p)``, zeros outside.
    """
    return warp_all([x], motion)[0][0]


def warp_all(buffers: Sequence[torch.Tensor], motion: torch.Tensor, keep: torch.Tensor | None = None
             ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """:func:`warp_to_current` of several buffers ``[B, C_i, H, W]`` with one sampling grid, and
    the :func:`coverage` of that grid.

    One ``grid_sample`` per buffer, no concatenation: the same numbers as warping their
    concatenation (bilinear sampling is per channel), without the full-resolution copies in
    and out of one stacked tensor. keep: bool ``[B, 1, 1, 1]`` or None; an item with False
    gets zeros and coverage 0 (its buffers are never read, :func:`sample_positions`).
    Returns ``(list of [B, C_i, H, W] float32, coverage [B, 1, H, W])``.
    """
    with torch.autocast(device_type=motion.device.type, enabled=False):
        sx, sy = sample_positions(motion, keep)
        grid = grid_from_positions(sx, sy)
        warped = [F.grid_sample(x.float(), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
                  for x in buffers]
        return warped, coverage(sx, sy)


# ----------------------------------------------------------------------------- export stub


class WarpHistoryOp(torch.autograd.Function):
    """The sampling of :meth:`denoiser.nn.temporal.TemporalRecurrence.warp` (before its gate)
    recorded as one ``denoiser::WarpHistory`` node (attributes ``motion_limit``, ``posinf``,
    ``outside``, ``cover_min``, ``channels_last``): the sample positions, bilinear weights and
    coverage computed once for every buffer; the value is the plain computation.

    forward(motion ``[B, 2, H, W]``, keep bool ``[B, 1, 1, 1]``, cover_min float, channels_last
    tuple of bools (one per buffer), buffer_0 ``[B, C_0, H, W]``, ...) -> (each buffer warped and
    divided by the coverage where it exceeds cover_min, else 0, float32, ``[B, C_i, H, W]``, or
    ``[B, H, W, C_i]`` (contiguous) where channels_last[i] (the layout of a convolution's input:
    the graph's permute back to ``[B, C_i, H, W]`` then moves nothing), ..., valid ``[B, 1, H,
    W]``: the coverage there, else 0).
    """

    @staticmethod
    def forward(ctx, motion, keep, cover_min, channels_last, *buffers):
        def plain():
            warped, cover = warp_all(buffers, motion, keep)
            ok = cover > cover_min
            safe = cover.clamp_min(cover_min)
            values = (torch.where(ok, v / safe, 0.0) for v in warped)
            return (*(v.permute(0, 2, 3, 1).contiguous() if last else v for v, last in zip(values, channels_last)),
                    torch.where(ok, cover, 0.0))

        return untraced(plain)

    @staticmethod
    def symbolic(g, motion, keep, cover_min, channels_last, *buffers):
        keep_f = g.op("Cast", keep, to_i=1)  # float32: 1 keep, 0 discard
        outs = graph_node(g, "WarpHistory", motion, keep_f, *buffers, like=motion, outputs=len(buffers) + 1,
                          motion_limit=float(MOTION_LIMIT), posinf=float(POSINF), outside=float(OUTSIDE),
                          cover_min=float(cover_min), channels_last=[int(bool(c)) for c in channels_last])
        sizes = motion.type().varyingSizes()  # [B, C_i, H, W] (None where not known)
        for out, like, last in zip(outs, [*buffers, None], [*channels_last, False]):
            channels = like.type().varyingSizes()[1] if like is not None and like.type().varyingSizes() else 1
            if sizes is not None and len(sizes) == 4:
                shape = [sizes[0], sizes[2], sizes[3], channels] if last else [sizes[0], channels, sizes[2], sizes[3]]
                out.setType(motion.type().with_sizes(shape))
            else:
                out.setType(motion.type())
        return outs
