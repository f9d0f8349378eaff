"""Sampler mixing labeled and unlabeled training windows in a fixed proportion."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import Sampler

from denoiser.errors import ConfigError


class MixedSampler(Sampler[int]):
    """Indices into ``ConcatDataset([labeled, unlabeled])``, a fraction ``ratio`` unlabeled.

    An epoch holds every labeled window once (shuffled) plus
    ``round(n_labeled * ratio / (1 - ratio))`` unlabeled windows drawn without replacement
    (with replacement when more are needed than exist), all shuffled together. ``ratio`` in
    ``[0, 1)``.
    """

    def __init__(self, n_labeled: int, n_unlabeled: int, ratio: float):
        if not 0.0 <= ratio < 1.0:
            raise ConfigError(f"data.unlabeled_ratio: must be in [0, 1), got {ratio}")
        if n_labeled < 1:
            raise ConfigError("data.use_unlabeled: the labeled training split has no windows")
        self.n_labeled = n_labeled
        self.n_unlabeled = n_unlabeled
        self.ratio = ratio
        self.n_drawn = round(n_labeled * ratio / (1.0 - ratio)) if n_unlabeled else 0

    def __len__(self) -> int:
        return self.n_labeled + self.n_drawn

    def __iter__(self) -> Iterator[int]:
        seed = int(torch.empty((), dtype=torch.int64).random_().item())
        g = torch.Generator().manual_seed(seed)
        labeled = torch.arange(self.n_labeled)
        if self.n_drawn <= self.n_unlabeled:
            unlabeled = torch.randperm(self.n_unlabeled, generator=g)[: self.n_drawn]
        else:
            unlabeled = torch.randint(0, self.n_unlabeled, (self.n_drawn,), generator=g)
        order = torch.cat([labeled, unlabeled + self.n_labeled])
        order = order[torch.randperm(len(order), generator=g)]
        return iter(order.tolist())
