"""Paired bootstrap intervals: is a network ahead of, tied with or behind a baseline?

Claims in the summaries compare two methods on the same test sequences. The differences are
paired (per sequence: network minus baseline), and the claim rests on a percentile bootstrap
interval of their mean over sequences, not on the two means alone: ``resamples`` draws of
``n`` sequences with replacement from a ``numpy.random.Generator`` with a fixed ``seed`` (the
same numbers on every run), the mean of each draw, and the ``(1 - confidence) / 2`` and
``(1 + confidence) / 2`` quantiles of those means (linear interpolation, ``numpy.quantile``'s
default).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: resamples, confidence and Generator seed of every interval a summary prints
RESAMPLES, CONFIDENCE, SEED = 10_000, 0.95, 0
#: the fewest paired items (sequences) a verdict other than ``tied`` needs
MIN_PAIRS = 2


@dataclass(frozen=True)
class PairedInterval:
    """The mean of the paired differences (network minus baseline) and its bootstrap interval."""

    mean: float
    lo: float
    hi: float
    n: int
    confidence: float

    @property
    def half_width(self) -> float:
        """Half the interval's width, ``(hi - lo) / 2``."""
        return (self.hi - self.lo) / 2

    def verdict(self, lower_is_better: bool = False) -> str:
        """``"ahead"`` when the whole interval is on the network's better side of 0, ``"behind"``
        when it is on the baseline's, else ``"tied"`` (for a lower-is-better metric the better
        side of the difference network minus baseline is below 0). Fewer than :data:`MIN_PAIRS`
        pairs are always ``"tied"``: one sequence's interval is its one difference, ``[x, x]``,
        which says nothing about a second sequence."""
        if self.n < MIN_PAIRS:
            return "tied"
        lo, hi = (-self.hi, -self.lo) if lower_is_better else (self.lo, self.hi)
        return "ahead" if lo > 0 else "behind" if hi < 0 else "tied"


def paired_interval(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE,
                    resamples: int = RESAMPLES, seed: int = SEED) -> PairedInterval:
    """Bootstrap interval of ``mean(a - b)``.

    a, b: ``[n]`` values of the two methods on the same ``n`` items (sequences), paired by
    position; ``n >= 1``. Identical inputs give ``[0, 0]``; a constant shift ``a = b + c``
    gives ``[c, c]``.
    """
    diff = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    if diff.ndim != 1 or diff.size == 0 or np.shape(a) != np.shape(b):
        raise ValueError(f"paired_interval: needs two equal-length, non-empty 1-D sequences, got "
                         f"shapes {np.shape(a)} and {np.shape(b)}")
    if not 0 < confidence < 1:
        raise ValueError(f"paired_interval: confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    means = diff[rng.integers(0, diff.size, size=(resamples, diff.size))].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - confidence) / 2, (1 + confidence) / 2])
    return PairedInterval(float(diff.mean()), float(lo), float(hi), int(diff.size), confidence)
