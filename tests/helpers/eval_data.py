"""Tiny procedural sequences written as real native-layout EXR files, for the command tests.

The content is analytic (so it is cheap and deterministic) but everything else is real: EXR
frames with every buffer of docs/design.md §3.1 and a validated ``sequence.json``, read back through
the data layer. The camera pans ``shift`` pixels per frame to the left, so the backward motion
is ``(+shift, 0)`` everywhere; the noisy color is the reference times a Gamma(spp)/spp factor
per pixel (the statistics of a mean of ``spp`` exponential samples), plus rare fireflies.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from denoiser.buffers import FRAME_INPUTS
from denoiser.data.exr import write_frame
from denoiser.data.sequence import write_sequence_json


def pattern(h: int, w: int, offset: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(reference [h, w, 3], albedo [h, w, 3])`` of a smooth HDR pattern shifted by ``offset``."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    xs = xs + offset
    freq = rng.uniform(0.08, 0.3, size=(3, 2))
    phase = rng.uniform(0, 6.28, size=3)
    albedo = np.stack([0.5 + 0.4 * np.sin(freq[c, 0] * xs + freq[c, 1] * ys + phase[c]) for c in range(3)], -1)
    light = 0.3 + 2.5 * np.exp(-(((xs % (w * 1.5)) - w * 0.6) ** 2 + (ys - h * 0.4) ** 2) / (0.1 * w * h))
    return (albedo * light[..., None]).astype(np.float32), albedo.astype(np.float32)


def write_sequence(directory: Path, frames: int = 4, size: int | tuple[int, int] = 32, seed: int = 0,
                   shift: float = 1.0, spp: int = 4, cuts: tuple[int, ...] = (), scene: str = "procedural") -> Path:
    """Write one native-layout sequence (``frame_XXXX.exr`` + ``sequence.json``) into ``directory``."""
    h, w = (size, size) if isinstance(size, int) else size
    rng = np.random.default_rng(seed + 1000)
    directory.mkdir(parents=True, exist_ok=True)
    for t in range(frames):
        reference, albedo = pattern(h, w, shift * t, seed)
        noise = rng.gamma(spp, 1.0 / spp, size=(h, w, 1)).astype(np.float32)
        color = reference * noise
        fireflies = rng.random((h, w)) < 0.005
        color[fireflies] *= 20.0
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = -1.0
        depth = np.full((h, w, 1), 5.0, np.float32)
        motion = np.zeros((h, w, 2), np.float32)
        motion[..., 0] = shift if t > 0 else 0.0
        write_frame(directory / f"frame_{t:04d}.exr", {"color": color, "albedo": albedo, "normal": normal,
                                                        "depth": depth, "motion": motion, "reference": reference})
    eye = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    write_sequence_json(directory, {
        "width": w, "height": h, "frames": frames, "spp": spp,
        "buffers": [*FRAME_INPUTS, "reference"],
        "cameras": [{"to_world": eye, "fov": 45.0} for _ in range(frames)], "cuts": list(cuts),
        "scene": {"name": scene, "effects": []},
        "renderer": {"name": "procedural-test", "version": "1", "variant": "numpy"},
        "seeds": {"noise": seed}, "render_seconds": {},
    })
    return directory


def write_dataset(root: Path, split: str = "test", sequences: int = 2, **kwargs) -> Path:
    """``sequences`` sequences ``seq_000 ...`` under ``<root>/<split>``; returns ``root``."""
    for i in range(sequences):
        write_sequence(root / split / f"seq_{i:03d}", seed=i, scene=f"scene{i % 2}", **kwargs)
    return root
