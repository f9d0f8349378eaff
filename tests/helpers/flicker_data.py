"""Tiny Blender-layout sequences with a known flicker, written as real Cycles-named EXR files, and
folders of "denoised" frames made from them (for the flicker command's tests).

A static camera looks at a textured wall (depth 10) while a textured square (depth 2) slides
right by ``STEP`` px per frame, uncovering the wall behind it. The Vector pass is exact, in
Blender's convention: (X, Y) = position in t-1 minus position in t, (Z, W) = position in t minus
position in t+1, +Y up. The noisy colour is the reference times per-pixel noise drawn anew
every frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from denoiser.data import exr

STEP = 2


def scene(t: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(reference [h, w, 3], depth [h, w], square mask [h, w])`` of frame t."""
    rng = np.random.default_rng(11)
    wall = rng.uniform(0.1, 3.0, (h, w, 3)).astype(np.float32)
    tile = rng.uniform(2.0, 8.0, (h // 3, h // 3, 3)).astype(np.float32)
    y0, x0 = h // 4, 2 + STEP * t
    img, depth, inside = wall.copy(), np.full((h, w), 10.0, np.float32), np.zeros((h, w), bool)
    ys, xs = slice(y0, y0 + tile.shape[0]), slice(x0, min(x0 + tile.shape[1], w))
    img[ys, xs] = tile[:, : xs.stop - xs.start]
    depth[ys, xs] = 2.0
    inside[ys, xs] = True
    return img, depth, inside


def write_blender_sequence(seq: Path, frames: int = 5, h: int = 18, w: int = 27, reference: bool = True,
                           vector: bool = True) -> Path:
    """``<seq>/noisy/0001.exr ...`` (and ``reference/``) as Cycles names its passes."""
    for t in range(frames):
        ref, depth, inside = scene(t, h, w)
        noisy = ref * np.random.default_rng(100 + t).gamma(4.0, 0.25, (h, w, 1)).astype(np.float32)
        ch = {f"ViewLayer.Combined.{c}": noisy[..., i] for i, c in enumerate("RGB")}
        ch["ViewLayer.Combined.A"] = np.ones((h, w), np.float32)
        ch.update({f"ViewLayer.Denoising Albedo.{c}": ref[..., i] / 8 for i, c in enumerate("RGB")})
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = -1.0
        ch.update({f"ViewLayer.Denoising Normal.{c}": normal[..., i] for i, c in enumerate("XYZ")})
        ch["ViewLayer.Depth.Z"] = depth
        if vector:
            vec = np.zeros((h, w, 4), np.float32)
            vec[inside, 0] = -STEP if t > 0 else 0.0
            vec[inside, 2] = -STEP
            ch.update({f"ViewLayer.Vector.{c}": vec[..., i] for i, c in enumerate("XYZW")})
        exr.write_channels(seq / "noisy" / f"{t + 1:04d}.exr", ch)
        if reference:
            exr.write_channels(seq / "reference" / f"{t + 1:04d}.exr",
                               {f"ViewLayer.Combined.{c}": ref[..., i] for i, c in enumerate("RGB")})
    return seq


def write_denoised(folder: Path, frames: int = 5, h: int = 18, w: int = 27, jitter: float = 0.0,
                   names=("R", "G", "B")) -> Path:
    """Frames ``0001.exr ...`` holding the reference times a per-frame gain ``1 ± jitter``
    (alternating), under the channel ``names``: a denoiser's output that flickers by ``jitter``."""
    for t in range(frames):
        ref, _, _ = scene(t, h, w)
        gain = 1.0 + jitter * (1 if t % 2 else -1)
        exr.write_channels(folder / f"{t + 1:04d}.exr", {n: ref[..., i] * gain for i, n in enumerate(names)})
    return folder
