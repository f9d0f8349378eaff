"""Deterministic seeds: one per sequence, and per frame and pass (and per sample) below it.

``sequence_seed(base, scene, split, index)`` mixes the dataset seed, the scene name, the split
and the sequence index with numpy's ``SeedSequence``; the same seed draws the scene's random
parameters. ``pass_seed(sequence, frame, role)`` gives Mitsuba's 32-bit sampler seed of one
pass: role 0 = noisy colour, 1 = reference, 2 + k = the k-th single-sample pass.
"""

from __future__ import annotations

import zlib

import numpy as np

NOISY, REFERENCE, FIRST_SAMPLE = 0, 1, 2


def _mix(*words: int) -> int:
    return int(np.random.SeedSequence([int(w) & 0xFFFFFFFF for w in words]).generate_state(1)[0])


def sequence_seed(base: int, scene: str, split: str, index: int) -> int:
    return _mix(base, zlib.crc32(scene.encode()), zlib.crc32(split.encode()), index)


def pass_seed(sequence: int, frame: int, role: int) -> int:
    return _mix(sequence, frame, role)
