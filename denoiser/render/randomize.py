"""Random parameters in scene configs, drawn from a numpy ``Generator`` seeded per sequence.

Any mapping with exactly one of these keys is replaced by a draw (recursively, depth first,
in config order, so one seed always gives the same scene):

* ``{uniform: [lo, hi]}``: uniform float; ``lo``/``hi`` may be lists (component-wise);
* ``{randint: [lo, hi]}``: integer in ``[lo, hi]`` inclusive;
* ``{choice: [a, b, ...]}``: one of the options (options may themselves be random specs);
* ``{hsv: [[h, s, v]_lo, [h, s, v]_hi]}``: an RGB colour drawn uniformly in HSV (h in [0, 1]).
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from denoiser.errors import ConfigError


def _uniform(rng: np.random.Generator, arg, where: str):
    lo, hi = _pair(arg, where, "uniform")
    out = rng.uniform(np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
    return out.tolist() if np.ndim(out) else float(out)


def _randint(rng: np.random.Generator, arg, where: str):
    lo, hi = _pair(arg, where, "randint")
    return int(rng.integers(int(lo), int(hi) + 1))


def _choice(rng: np.random.Generator, arg, where: str):
    if not isinstance(arg, list) or not arg:
        raise ConfigError(f"{where}: 'choice' needs a non-empty list")
    return resolve(arg[int(rng.integers(len(arg)))], rng, where)


def _hsv(rng: np.random.Generator, arg, where: str):
    lo, hi = _pair(arg, where, "hsv")
    h, s, v = rng.uniform(np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
    return [float(c) for c in colorsys.hsv_to_rgb(h % 1.0, s, v)]


SAMPLERS: dict[str, Callable] = {"uniform": _uniform, "randint": _randint, "choice": _choice, "hsv": _hsv}


def _pair(arg, where: str, kind: str):
    if not isinstance(arg, list) or len(arg) != 2:
        raise ConfigError(f"{where}: '{kind}' needs [lo, hi], got {arg!r}")
    return arg


def resolve(node: Any, rng: np.random.Generator, where: str = "scene") -> Any:
    """Return a copy of ``node`` (plain dicts/lists/scalars) with every random spec drawn."""
    if isinstance(node, Mapping):
        if len(node) == 1:
            key = next(iter(node))
            if key in SAMPLERS:
                return SAMPLERS[key](rng, node[key], where)
        return {k: resolve(v, rng, f"{where}.{k}") for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [resolve(v, rng, f"{where}[{i}]") for i, v in enumerate(node)]
    return node
