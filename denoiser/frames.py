"""Frames for timing, probing and tests: random frames, and one frame resampled to any size.

A frame is ``{buffer: [B, C, H, W]}`` float32 tensors (vocabulary: :mod:`denoiser.buffers`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from denoiser.buffers import CHANNELS, FRAME_INPUTS


@dataclass(frozen=True)
class FrameRecipe:
    """How :func:`random_frame` draws each buffer ``[B, C, H, W]`` (``rand``: U[0, 1), ``randn``: N(0, 1)).

    * ``color = rand ** color_power * color_scale``, times ``firefly_gain`` where a ``[B, 1, H, W]``
      ``rand`` drawn right after it is below ``fireflies``;
    * ``albedo = rand``; ``normal = randn`` normalised over channels (unit length);
    * ``depth = rand * (hi - lo) + lo`` for ``depth = (lo, hi)``, ``sky_depth`` where a
      ``[B, 1, H, W]`` ``rand`` drawn right after it is below ``sky``;
    * ``motion = randn * motion_scale`` pixels, times ``max(H, W)`` when ``motion_per_size``.

    ``draw_first`` names buffers drawn before the others, which follow in
    :data:`~denoiser.buffers.FRAME_INPUTS` order (the draw order fixes the values of a seed).
    """

    color_scale: float = 2.0
    color_power: float = 1.0
    fireflies: float = 0.0
    firefly_gain: float = 50.0
    depth: tuple[float, float] = (1.0, 11.0)
    sky: float = 0.0
    sky_depth: float = 1e10
    motion_scale: float = 1.0
    motion_per_size: bool = False
    draw_first: tuple[str, ...] = ()


#: Named recipes. ``plain``: HDR-ish colour, depth in [1, 11), unit motion (network tests, FLOP
#: counts); ``hard``: fireflies (1% x50), sky depth (10% at 1e10), motion up to a quarter of the
#: frame (the ONNX export and its check); ``probe``: depth in [1, 6) (tracing for parameter
#: transfer and feature shapes). Each draws exactly what its former helper drew, so seeds give
#: the same frames as before.
RECIPES = {
    "plain": FrameRecipe(),
    "hard": FrameRecipe(color_scale=4.0, color_power=2.0, fireflies=0.01, depth=(0.5, 20.5), sky=0.1,
                        motion_scale=0.25, motion_per_size=True, draw_first=("color", "depth")),
    "probe": FrameRecipe(depth=(1.0, 6.0), draw_first=("normal",)),
}


def random_frame(batch: int, height: int, width: int, seed: int = 0, *, kind: str | FrameRecipe = "plain",
                 samples: int = 0) -> dict[str, torch.Tensor]:
    """A random frame ``{buffer: [B, C, H, W]}`` over :data:`~denoiser.buffers.FRAME_INPUTS`.

    ``kind``: a name of :data:`RECIPES` or a :class:`FrameRecipe`. ``samples`` > 0 adds
    per-sample radiance ``samples [B, S, 3, H, W]`` (``rand * color_scale``), drawn last.
    The values depend only on the arguments (own generator seeded with ``seed``).
    """
    recipe = RECIPES[kind] if isinstance(kind, str) else kind
    g = torch.Generator().manual_seed(seed)

    def rand(channels: int) -> torch.Tensor:
        return torch.rand(batch, channels, height, width, generator=g)

    def draw(name: str) -> torch.Tensor:
        if name == "color":
            color = rand(CHANNELS[name])
            if recipe.color_power != 1:
                color = color ** recipe.color_power
            color = color * recipe.color_scale
            if recipe.fireflies:
                color = torch.where(rand(1) < recipe.fireflies, color * recipe.firefly_gain, color)
            return color
        if name == "normal":
            return F.normalize(torch.randn(batch, CHANNELS[name], height, width, generator=g), dim=1)
        if name == "depth":
            lo, hi = recipe.depth
            depth = rand(CHANNELS[name]) * (hi - lo) + lo
            if recipe.sky:
                depth = torch.where(rand(1) < recipe.sky, torch.full_like(depth, recipe.sky_depth), depth)
            return depth
        if name == "motion":
            motion = torch.randn(batch, CHANNELS[name], height, width, generator=g) * recipe.motion_scale
            return motion * max(height, width) if recipe.motion_per_size else motion
        return rand(CHANNELS[name])

    order = [*recipe.draw_first, *(k for k in FRAME_INPUTS if k not in recipe.draw_first)]
    drawn = {name: draw(name) for name in order}
    frame = {name: drawn[name] for name in FRAME_INPUTS}
    if samples:
        frame["samples"] = torch.rand(batch, samples, CHANNELS["color"], height, width, generator=g) \
            * recipe.color_scale
    return frame


def resize_frame(frame: Mapping[str, torch.Tensor], height: int, width: int) -> dict[str, torch.Tensor]:
    """Resample a frame ``{buffer: [1, C, h, w]}`` (``samples [1, S, 3, h, w]``) to ``height`` x ``width``.

    Bilinear for every buffer; normals are re-normalised (zero stays zero), motion vectors are
    scaled with the image. Used to put the same content at every benchmark size.
    """
    h, w = frame["color"].shape[-2:]
    out = {}
    for k, v in frame.items():
        flat = v.flatten(1, 2) if v.dim() == 5 else v  # samples [1, S, 3, h, w]: every sample alike
        r = flat if (h, w) == (height, width) else F.interpolate(flat.float(), size=(height, width), mode="bilinear",
                                                                   align_corners=False)
        if k == "normal":
            r = F.normalize(r, dim=1) * (v.abs().amax(dim=1, keepdim=True).amax() > 0)
        elif k == "motion":
            r = r * torch.tensor([width / w, height / h]).view(1, 2, 1, 1)
        out[k] = r.reshape(*v.shape[:-2], height, width).contiguous()
    return out
