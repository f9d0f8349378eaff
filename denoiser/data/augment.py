"""Augmentations that keep the meaning of every buffer (one draw per window, all frames alike).

Works on an item of :class:`~denoiser.data.dataset.WindowDataset`: tensors ``[T, C, H, W]``
(``samples``: ``[T, S, 3, H, W]``); channel axis -3, image axes -2 (y, down) and -1 (x, right).

* horizontal flip (x -> W-1-x): ``motion.x`` and ``normal.x`` change sign;
* vertical flip (y -> H-1-y): ``motion.y`` and ``normal.y`` change sign (motion y points down,
  normal y points up; a mirror negates both);
* transpose (x <-> y, only for square crops so batches keep one shape): motion
  ``(mx, my) -> (my, mx)`` (both in image axes); normal ``(nx, ny, nz) -> (-ny, -nx, nz)``
  (normal y points up, i.e. against image y, so the swap carries two sign changes);
* exposure: ``color``, ``samples`` and ``reference`` are multiplied by one factor drawn
  log-uniformly from ``exposure = [lo, hi]`` (albedo, normals, depth, motion unchanged);
* channel permutation: one random permutation of R, G, B applied to ``color``, ``samples``,
  ``albedo`` and ``reference``.

Depth is planar (unchanged by mirrors). Random draws use torch's generator (``generator``
argument, else the global one, which DataLoader seeds per worker).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

#: Buffers that hold radiance (scaled by exposure).
RADIANCE = ("color", "samples", "reference")
#: Buffers whose channels are R, G, B (permuted together).
RGB = ("color", "samples", "albedo", "reference")
#: Image buffers (every spatial transform applies).
IMAGES = ("color", "samples", "albedo", "normal", "depth", "motion", "reference")


def hflip(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Mirror left-right: ``x -> W-1-x``; negates ``motion[..., 0]`` and ``normal[..., 0]``."""
    out = dict(item)
    for k in IMAGES:
        if k in out:
            out[k] = out[k].flip(-1)
    for k in ("motion", "normal"):
        if k in out:
            out[k] = out[k].clone()
            out[k][..., 0, :, :] *= -1
    return out


def vflip(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Mirror top-bottom: ``y -> H-1-y``; negates ``motion[..., 1]`` and ``normal[..., 1]``."""
    out = dict(item)
    for k in IMAGES:
        if k in out:
            out[k] = out[k].flip(-2)
    for k in ("motion", "normal"):
        if k in out:
            out[k] = out[k].clone()
            out[k][..., 1, :, :] *= -1
    return out


def transpose(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Swap image axes (pixel (x, y) -> (y, x)); motion ``(my, mx)``, normal ``(-ny, -nx, nz)``."""
    out = dict(item)
    for k in IMAGES:
        if k in out:
            out[k] = out[k].transpose(-1, -2)
    if "motion" in out:
        m = out["motion"]
        out["motion"] = torch.stack([m[..., 1, :, :], m[..., 0, :, :]], dim=-3)
    if "normal" in out:
        n = out["normal"]
        out["normal"] = torch.stack([-n[..., 1, :, :], -n[..., 0, :, :], n[..., 2, :, :]], dim=-3)
    for k in IMAGES:
        if k in out:
            out[k] = out[k].contiguous()
    return out


def scale_exposure(item: dict[str, torch.Tensor], factor: float) -> dict[str, torch.Tensor]:
    """Multiply ``color``, ``samples`` and ``reference`` by ``factor``."""
    out = dict(item)
    for k in RADIANCE:
        if k in out:
            out[k] = out[k] * factor
    return out


def permute_channels(item: dict[str, torch.Tensor], perm: Sequence[int]) -> dict[str, torch.Tensor]:
    """Reorder R, G, B of ``color``, ``samples``, ``albedo``, ``reference`` by ``perm``."""
    out = dict(item)
    idx = torch.as_tensor(list(perm), dtype=torch.long)
    for k in RGB:
        if k in out:
            out[k] = out[k].index_select(-3, idx)
    return out


class Augment:
    """Random, meaning-preserving augmentation of one training window (config ``data.augment``).

    ``flip``: random horizontal and vertical flips (each with probability 1/2); ``transpose``:
    random axis swap (probability 1/2, square crops only); ``exposure``: ``[lo, hi]`` range of
    the log-uniform exposure factor, or null; ``permute_channels``: random RGB permutation.
    """

    def __init__(self, flip: bool = True, transpose: bool = True, exposure: Sequence[float] | None = None,
                 permute_channels: bool = False):
        self.flip = bool(flip)
        self.transpose = bool(transpose)
        if exposure is not None:
            lo, hi = (float(v) for v in exposure)
            if not 0 < lo <= hi:
                from denoiser.errors import ConfigError

                raise ConfigError(f"data.augment.exposure: need 0 < lo <= hi, got {list(exposure)}")
            exposure = (lo, hi)
        self.exposure = exposure
        self.permute = bool(permute_channels)

    def __call__(self, item: Mapping[str, torch.Tensor], generator: torch.Generator | None = None) -> dict:
        out = dict(item)

        def coin() -> bool:
            return bool(torch.randint(0, 2, (), generator=generator))

        if self.transpose and coin():
            h, w = out["color"].shape[-2:]
            if h == w:
                out = transpose(out)
        if self.flip and coin():
            out = hflip(out)
        if self.flip and coin():
            out = vflip(out)
        if self.exposure is not None:
            lo, hi = self.exposure
            u = float(torch.rand((), generator=generator))
            out = scale_exposure(out, math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))
        if self.permute:
            out = permute_channels(out, torch.randperm(3, generator=generator).tolist())
        return out

    def __repr__(self) -> str:
        return (f"Augment(flip={self.flip}, transpose={self.transpose}, exposure={self.exposure}, "
                f"permute_channels={self.permute})")
