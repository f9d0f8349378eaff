"""Augmentations that keep the meaning of every buffer (one draw per window, all frames alike).

Works on an item of :class:`~denoiser.data.dataset.WindowDataset`: arrays ``[T, C, H, W]``
(``samples``: ``[T, S, 3, H, W]``); channel axis -3, image axes -2 (y, down) and -1 (x, right).
Items may hold numpy arrays (the dataset augments before building tensors: flips and
transposes are then free views and one copy follows) or torch tensors (same results).

* horizontal flip (x -> W-1-x): ``motion.x`` and ``normal.x`` change sign;
* vertical flip (y -> H-1-y): ``motion.y`` and ``normal.y`` change sign (motion y points down,
  normal y points up; a mirror negates both);
* transpose (x <-> y, only for square crops so batches keep one shape): motion
  ``(mx, my) -> (my, mx)`` (both in image axes); normal ``(nx, ny, nz) -> (-ny, -nx, nz)``
  (normal y points up, i.e. against image y, so the swap carries two sign changes);
* exposure: ``color``, ``samples`` and ``reference`` are multiplied by one factor drawn
  log-uniformly from ``exposure = [lo, hi]`` (albedo, normals, depth, motion unchanged);
* channel permutation: one random permutation of R, G, B applied to ``color``, ``samples``,
  ``albedo`` and ``reference``;
* noise scale (labeled items only, with probability ``noise_scale_prob``): ``color`` (and each of
  ``samples``) becomes ``reference + f * (color - reference)`` for one ``f`` drawn log-uniformly
  from ``noise_scale = [lo, hi]``, ``0 < lo <= hi <= 1``. The residual is scaled by ``f``, so its
  variance is that of a render with ``spp / f^2`` samples: the network sees inputs cleaner than
  the dataset's own and learns to keep what a cleaner input already has (an unbiased estimate
  stays unbiased; with ``f <= 1`` the result is a convex mix of two non-negative images, so it
  stays non-negative). Unlabeled items (no reference, or ``labeled`` false) are left as they are.

Depth is planar (unchanged by mirrors). Random draws use torch's generator (``generator``
argument, else the global one, which DataLoader seeds per worker). The pixel work is numpy:
single-threaded, so it does not fight the training process for cores.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from denoiser.buffers import RADIANCE_BUFFERS, RGB_BUFFERS, SEQUENCE_BUFFERS

#: Buffers that hold radiance (scaled by exposure), whose channels are R, G, B (permuted together),
#: and image buffers (every spatial transform applies).
RADIANCE, RGB, IMAGES = RADIANCE_BUFFERS, RGB_BUFFERS, SEQUENCE_BUFFERS

Arrays = dict[str, np.ndarray]


def _on_arrays(item: Mapping, fn: Callable[[Arrays], Arrays]) -> dict:
    """Apply ``fn`` to the image buffers of ``item`` as numpy arrays; keep each buffer's type."""
    out = dict(item)
    arrays = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in item.items() if k in IMAGES}
    for k, v in fn(arrays).items():
        out[k] = torch.from_numpy(np.ascontiguousarray(v)) if isinstance(item[k], torch.Tensor) else v
    return out


def _signs(x: np.ndarray, signs: Sequence[float]) -> np.ndarray:
    """Multiply the channels (axis -3) of ``x`` by ``signs``."""
    return x * np.asarray(signs, dtype=x.dtype).reshape(-1, 1, 1)


def hflip(item: Mapping) -> dict:
    """Mirror left-right: ``x -> W-1-x``; negates ``motion[..., 0]`` and ``normal[..., 0]``."""

    def fn(a: Arrays) -> Arrays:
        a = {k: v[..., ::-1] for k, v in a.items()}
        if "motion" in a:
            a["motion"] = _signs(a["motion"], (-1, 1))
        if "normal" in a:
            a["normal"] = _signs(a["normal"], (-1, 1, 1))
        return a

    return _on_arrays(item, fn)


def vflip(item: Mapping) -> dict:
    """Mirror top-bottom: ``y -> H-1-y``; negates ``motion[..., 1]`` and ``normal[..., 1]``."""

    def fn(a: Arrays) -> Arrays:
        a = {k: v[..., ::-1, :] for k, v in a.items()}
        if "motion" in a:
            a["motion"] = _signs(a["motion"], (1, -1))
        if "normal" in a:
            a["normal"] = _signs(a["normal"], (1, -1, 1))
        return a

    return _on_arrays(item, fn)


def transpose(item: Mapping) -> dict:
    """Swap image axes (pixel (x, y) -> (y, x)); motion ``(my, mx)``, normal ``(-ny, -nx, nz)``."""

    def fn(a: Arrays) -> Arrays:
        a = {k: v.swapaxes(-1, -2) for k, v in a.items()}
        if "motion" in a:
            a["motion"] = a["motion"][..., [1, 0], :, :]
        if "normal" in a:
            a["normal"] = _signs(a["normal"][..., [1, 0, 2], :, :], (-1, -1, 1))
        return a

    return _on_arrays(item, fn)


def scale_exposure(item: Mapping, factor: float) -> dict:
    """Multiply ``color``, ``samples`` and ``reference`` by ``factor``."""
    return _on_arrays(item, lambda a: {k: a[k] * np.float32(factor) for k in RADIANCE if k in a})


def scale_noise(item: Mapping, factor: float) -> dict:
    """``color`` and ``samples`` -> ``reference + factor * (x - reference)`` (``samples``
    ``[T, S, 3, H, W]`` against ``reference [T, 3, H, W]``)."""

    def fn(a: Arrays) -> Arrays:
        ref = a["reference"]
        out = {"color": ref + np.float32(factor) * (a["color"] - ref)}
        if "samples" in a:
            out["samples"] = ref[:, None] + np.float32(factor) * (a["samples"] - ref[:, None])
        return out

    return _on_arrays(item, fn)


def permute_channels(item: Mapping, perm: Sequence[int]) -> dict:
    """Reorder R, G, B of ``color``, ``samples``, ``albedo``, ``reference`` by ``perm``."""
    idx = list(perm)
    return _on_arrays(item, lambda a: {k: a[k][..., idx, :, :] for k in RGB if k in a})


class Augment:
    """Random, meaning-preserving augmentation of one training window (config ``data.augment``).

    ``flip``: random horizontal and vertical flips (each with probability 1/2); ``transpose``:
    random axis swap (probability 1/2, square crops only); ``exposure``: ``[lo, hi]`` range of
    the log-uniform exposure factor, or null; ``permute_channels``: random RGB permutation;
    ``noise_scale``: ``[lo, hi]`` range of the log-uniform residual factor of labeled items
    (module docstring), or null; ``noise_scale_prob``: the chance that a labeled window gets it.
    """

    def __init__(self, flip: bool = True, transpose: bool = True, exposure: Sequence[float] | None = None,
                 permute_channels: bool = False, noise_scale: Sequence[float] | None = None,
                 noise_scale_prob: float = 1.0):
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
        if noise_scale is not None:
            lo, hi = (float(v) for v in noise_scale)
            if not 0 < lo <= hi <= 1:
                from denoiser.errors import ConfigError

                raise ConfigError(f"data.augment.noise_scale: need 0 < lo <= hi <= 1, got {list(noise_scale)}")
            noise_scale = (lo, hi)
        if not 0 <= float(noise_scale_prob) <= 1:
            from denoiser.errors import ConfigError

            raise ConfigError(f"data.augment.noise_scale_prob: need a probability in [0, 1], got {noise_scale_prob}")
        self.noise_scale = noise_scale
        self.noise_prob = float(noise_scale_prob)

    def __call__(self, item: Mapping, generator: torch.Generator | None = None) -> dict:
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
        if self.noise_scale is not None and "reference" in out and bool(out.get("labeled", True)) \
                and float(torch.rand((), generator=generator)) < self.noise_prob:  # drawn only when on
            lo, hi = self.noise_scale
            u = float(torch.rand((), generator=generator))
            out = scale_noise(out, math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))
        return out

    def __repr__(self) -> str:
        return (f"Augment(flip={self.flip}, transpose={self.transpose}, exposure={self.exposure}, "
                f"permute_channels={self.permute}, noise_scale={self.noise_scale}, noise_scale_prob={self.noise_prob})")
