"""Frames for timing and probing: the same content resampled to any size.

A frame is ``{buffer: [B, C, H, W]}`` float32 tensors (vocabulary: :mod:`denoiser.buffers`).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F


def resize_frame(frame: Mapping[str, torch.Tensor], height: int, width: int) -> dict[str, torch.Tensor]:
    """Resample a frame ``{buffer: [1, C, h, w]}`` to ``height`` x ``width``.

    Bilinear for every buffer; normals are re-normalised (zero stays zero), motion vectors are
    scaled with the image. Used to put the same content at every benchmark size.
    """
    h, w = frame["color"].shape[-2:]
    out = {}
    for k, v in frame.items():
        r = v if (h, w) == (height, width) else F.interpolate(v.float(), size=(height, width), mode="bilinear",
                                                                align_corners=False)
        if k == "normal":
            r = F.normalize(r, dim=1) * (v.abs().amax(dim=1, keepdim=True).amax() > 0)
        elif k == "motion":
            r = r * torch.tensor([width / w, height / h]).view(1, 2, 1, 1)
        out[k] = r.contiguous()
    return out
