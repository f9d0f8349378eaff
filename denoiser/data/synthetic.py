"""Synthetic native-layout sequences with exactly known motion (tests, benchmark, smoke runs).

Every frame is the previous one warped by an integer, blockwise-constant backward motion
field: ``buffer_t[p] = buffer_{t-1}[p + motion_t(p)]`` (coordinates clamped at the border) for
``reference``, ``albedo`` and ``depth``. So warping frame t-1 by ``motion_t`` reproduces frame
t exactly wherever ``p + motion_t(p)`` is inside the image. ``normal`` is derived from depth by
:func:`normal_from_depth`; ``color`` is the reference plus independent per-frame noise (and
``samples`` average to ``color``). At a cut the content is drawn anew and motion is zero.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from denoiser.buffers import FRAME_INPUTS
from denoiser.data.exr import write_frame
from denoiser.data.sequence import write_sequence_json


def normal_from_depth(depth: np.ndarray) -> np.ndarray:
    """Camera-space unit normals ``[H, W, 3]`` of the surface ``z = depth[y, x]`` ``[H, W]``.

    Pixel (x, y) sits at camera-space (x, -y, depth) (x right, y up, z into the scene; y down
    in the image). The normal facing the camera is ``normalize(d_x, -d_y, -1)`` with central
    differences ``d_x, d_y`` along image x and y (``np.gradient``).
    """
    dy, dx = np.gradient(depth.astype(np.float64))
    n = np.stack([dx, -dy, -np.ones_like(dx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def block_motion(rng: np.random.Generator, height: int, width: int, block: int = 8, amplitude: int = 2) -> np.ndarray:
    """Integer backward motion ``[H, W, 2]`` (x, y), constant on ``block`` x ``block`` tiles."""
    by, bx = -(-height // block), -(-width // block)
    tiles = rng.integers(-amplitude, amplitude + 1, size=(by, bx, 2))
    return np.repeat(np.repeat(tiles, block, 0), block, 1)[:height, :width].astype(np.float32)


def warp_nearest(prev: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """``out[p] = prev[clamp(p + motion(p))]`` for integer motion; ``prev`` ``[H, W, C]``."""
    h, w = prev.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    sx = np.clip(xs + motion[..., 0].astype(int), 0, w - 1)
    sy = np.clip(ys + motion[..., 1].astype(int), 0, h - 1)
    return prev[sy, sx]


def _content(rng: np.random.Generator, h: int, w: int) -> dict[str, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    f = rng.uniform(0.02, 0.2, size=4)
    reference = np.stack([1.5 + np.sin(xx * f[0] + c) * np.cos(yy * f[1] - c) for c in (0.0, 1.0, 2.0)], -1)
    reference = reference * rng.uniform(0.2, 3.0, size=3) + rng.uniform(0, 0.3, size=(h, w, 3))
    albedo = rng.uniform(0.05, 0.95, size=(h, w, 3))
    depth = 5.0 + np.sin(xx * f[2]) * np.cos(yy * f[3]) + rng.uniform(0, 0.05, size=(h, w))
    return {"reference": reference.astype(np.float32), "albedo": albedo.astype(np.float32),
            "depth": depth[..., None].astype(np.float32)}


def write_synthetic_sequence(
    directory: str | os.PathLike, frames: int = 4, width: int = 32, height: int = 32, *,
    labeled: bool = True, samples: int = 0, cuts: Sequence[int] = (), seed: int = 0, half: bool = False,
    compression: str = "zip", spp: int = 4, scene: str = "synthetic", block: int = 8,
) -> dict[str, list[np.ndarray]]:
    """Write ``frame_XXXX.exr`` + ``sequence.json`` into ``directory``; return the buffers.

    Returns ``{buffer: [per-frame array [H, W, C]]}`` as written (``samples``: ``[S, H, W, 3]``),
    so tests can compare what they read with what was written.
    """
    directory = Path(directory)
    rng = np.random.default_rng(seed)
    written: dict[str, list[np.ndarray]] = {}
    state = None
    for t in range(frames):
        if state is None or t in cuts:
            state = _content(rng, height, width)
            motion = np.zeros((height, width, 2), np.float32)
        else:
            motion = block_motion(rng, height, width, block)
            state = {k: warp_nearest(v, motion) for k, v in state.items()}
        noise = rng.normal(0.0, 0.3, size=(max(samples, 1), height, width, 3)).astype(np.float32)
        per_sample = np.maximum(state["reference"][None] * (1 + noise), 0).astype(np.float32)
        bufs = {
            "color": per_sample.mean(axis=0),
            "albedo": state["albedo"],
            "normal": normal_from_depth(state["depth"][..., 0]),
            "depth": state["depth"],
            "motion": motion,
        }
        if samples:
            bufs["samples"] = per_sample
        if labeled:
            bufs["reference"] = state["reference"]
        write_frame(directory / f"frame_{t:04d}.exr", bufs, half=half, compression=compression)
        for k, v in bufs.items():
            written.setdefault(k, []).append(v)
    names = list(FRAME_INPUTS) + (["samples"] if samples else []) + (
        ["reference"] if labeled else [])
    eye = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    write_sequence_json(directory, {
        "width": width, "height": height, "frames": frames, "spp": spp, "buffers": names,
        "sample_count": samples, "cameras": [{"to_world": eye, "fov": 45.0} for _ in range(frames)],
        "cuts": sorted(set(cuts) - {0}), "scene": {"name": scene, "effects": []},
        "renderer": {"name": "synthetic", "version": "1", "variant": "numpy"},
        "seeds": {"content": seed}, "render_seconds": {"color": 0.0},
    })
    return written
