"""Procedural textures generated in numpy (float32 ``[H, W, 3]`` linear RGB bitmaps).

A texture is given in place of a colour: ``color: {texture: checker, color0: [...],
color1: [...], tiles: 8}``. Using one needs the ``textures`` effect. Kinds: ``checker``
(tiles x tiles squares), ``stripes`` (``tiles`` bands), ``noise`` (smooth value noise with
``seed`` and ``octaves``), ``bricks`` (``tiles`` rows, mortar colour ``color1``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from functools import lru_cache
from typing import Any

import numpy as np

from denoiser.errors import ConfigError

RESOLUTION = 256


def _lerp(c0, c1, t: np.ndarray) -> np.ndarray:
    c0 = np.asarray(c0, dtype=np.float32)
    c1 = np.asarray(c1, dtype=np.float32)
    return (c0 * (1 - t[..., None]) + c1 * t[..., None]).astype(np.float32)


def checker(color0=(0.8, 0.8, 0.8), color1=(0.1, 0.1, 0.1), tiles: int = 8) -> np.ndarray:
    i = (np.arange(RESOLUTION) * tiles // RESOLUTION)
    mask = ((i[:, None] + i[None, :]) % 2).astype(np.float32)
    return _lerp(color0, color1, mask)


def stripes(color0=(0.8, 0.8, 0.8), color1=(0.1, 0.1, 0.1), tiles: int = 8) -> np.ndarray:
    i = (np.arange(RESOLUTION) * tiles // RESOLUTION) % 2
    return _lerp(color0, color1, np.broadcast_to(i[None, :].astype(np.float32), (RESOLUTION, RESOLUTION)))


def noise(color0=(0.8, 0.8, 0.8), color1=(0.1, 0.1, 0.1), tiles: int = 4, octaves: int = 4,
          seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(int(seed))
    acc = np.zeros((RESOLUTION, RESOLUTION), np.float32)
    total = 0.0
    for o in range(int(octaves)):
        n = int(tiles) * 2 ** o
        grid = rng.random((n + 1, n + 1)).astype(np.float32)
        grid[-1, :], grid[:, -1] = grid[0, :], grid[:, 0]  # tileable
        x = np.linspace(0, n, RESOLUTION, endpoint=False)
        i0 = x.astype(int)
        f = x - i0
        f = f * f * (3 - 2 * f)
        rows = grid[i0] * (1 - f)[:, None] + grid[i0 + 1] * f[:, None]
        img = rows[:, i0] * (1 - f)[None, :] + rows[:, i0 + 1] * f[None, :]
        acc += img * 0.5 ** o
        total += 0.5 ** o
    return _lerp(color0, color1, acc / total)


def bricks(color0=(0.6, 0.25, 0.15), color1=(0.85, 0.85, 0.8), tiles: int = 8) -> np.ndarray:
    y = np.arange(RESOLUTION) * tiles / RESOLUTION
    x = np.arange(RESOLUTION) * tiles / (2 * RESOLUTION)
    row = y.astype(int)
    xs = x[None, :] + 0.5 * (row[:, None] % 2)
    mortar = ((y % 1.0)[:, None] < 0.08) | ((xs % 1.0) < 0.04)
    return _lerp(color0, color1, mortar.astype(np.float32))


KINDS: dict[str, Callable[..., np.ndarray]] = {"checker": checker, "stripes": stripes, "noise": noise,
                                               "bricks": bricks}
#: Textures whose edges should stay sharp (nearest-neighbour lookup).
SHARP = {"checker", "stripes", "bricks"}


@lru_cache(maxsize=64)
def _generate(key: str) -> np.ndarray:
    params = json.loads(key)
    kind = params.pop("texture")
    return KINDS[kind](**params)


def texture_array(params: Mapping[str, Any], where: str) -> np.ndarray:
    """The bitmap ``[RESOLUTION, RESOLUTION, 3]`` of a texture spec (cached per spec)."""
    kind = params.get("texture")
    if kind not in KINDS:
        raise ConfigError(f"{where}: unknown texture {kind!r}; known: {', '.join(KINDS)}")
    try:
        return _generate(json.dumps(dict(params), sort_keys=True))
    except TypeError as exc:
        raise ConfigError(f"{where}: bad texture parameters ({exc})") from None
