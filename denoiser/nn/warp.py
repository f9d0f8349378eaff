"""Backward warping with motion vectors (docs/design.md §3.1 convention).

The surface seen at pixel centre ``p`` in frame t was at ``p + motion(p)`` in frame t-1
(pixels; x to the right, y downward). ``warp_to_current`` therefore samples the previous
frame's buffer at ``p + motion(p)`` with bilinear ``grid_sample`` and zeros outside the image.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from denoiser.nn.inputs import sanitize

#: motion is clamped to +-(MOTION_LIMIT * max(H, W)) pixels: anything beyond is off-screen
#: anyway, and the clamp keeps grid coordinates small and finite.
MOTION_LIMIT = 4.0


def sampling_grid(motion: torch.Tensor) -> torch.Tensor:
    """Normalised ``grid_sample`` grid for backward motion.

    motion: ``[B, 2, H, W]`` pixels (x right, y down; NaN, -Inf -> 0, +Inf -> 65504) -> ``[B, H, W, 2]`` float32 in
    ``align_corners=False`` convention: ``g = (p + motion + 0.5) * 2 / size - 1``.
    """
    h, w = motion.shape[-2:]
    limit = MOTION_LIMIT * max(h, w)
    m = sanitize(motion).clamp(-limit, limit)
    ys = torch.arange(h, device=motion.device, dtype=torch.float32).view(1, 1, h, 1)
    xs = torch.arange(w, device=motion.device, dtype=torch.float32).view(1, 1, 1, w)
    gx = (xs + m[:, 0:1] + 0.5) * (2.0 / w) - 1.0
    gy = (ys + m[:, 1:2] + 0.5) * (2.0 / h) - 1.0
    # [B, 2, H, W] then one transpose to [B, H, W, 2]: stacking x and y along a new last axis
    # is an interleaving copy that inference engines run slowly (OpenVINO: a reference Concat)
    return torch.cat([gx, gy], dim=1).permute(0, 2, 3, 1)


def warp_to_current(x: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Warp the previous frame's buffer to the current frame.

    x: ``[B, C, H, W]`` buffer of frame t-1; motion: ``[B, 2, H, W]`` backward motion of frame t.
    Returns ``[B, C, H, W]`` float32: ``x`` sampled bilinearly at ``p + motion(p)``, zeros outside.
    """
    return warp_all([x], motion)[0]


def warp_all(buffers: Sequence[torch.Tensor], motion: torch.Tensor) -> list[torch.Tensor]:
    """:func:`warp_to_current` of several buffers ``[B, C_i, H, W]`` with one sampling grid.

    One ``grid_sample`` per buffer, no concatenation: the same numbers as warping their
    concatenation (bilinear sampling is per channel), without the full-resolution copies in
    and out of one stacked tensor. Returns a list of ``[B, C_i, H, W]`` float32.
    """
    with torch.autocast(device_type=motion.device.type, enabled=False):
        grid = sampling_grid(motion)
        return [F.grid_sample(x.float(), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
                for x in buffers]
