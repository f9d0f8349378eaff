"""Samplers: labeled and unlabeled training windows mixed in a fixed proportion
(:class:`MixedSampler`); groups of training windows drawn in fixed shares, e.g. the families of
``data.extra_roots`` against the main root's (:class:`ShareSampler`); validation/test sequences
sharded whole over DDP ranks (:class:`SequenceShardSampler`)."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import Sampler
from torch.utils.data.distributed import DistributedSampler

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


class ShareSampler(Sampler[int]):
    """Indices drawn from groups in fixed shares: ``length`` per epoch, ``shares[g]`` of them from
    ``groups[g]`` (a list of dataset indices), all shuffled together.

    A group's count is its share of ``length`` rounded so the counts add up to ``length`` (largest
    remainders first); it is drawn without replacement, whole shuffled passes over the group
    followed by a partial one, so every index of a group is drawn before any is drawn twice.
    ``shares`` are >= 0 and sum to 1; a group with a positive share must not be empty.
    """

    def __init__(self, groups: list[list[int]], shares: list[float], length: int):
        if len(groups) != len(shares) or not groups:
            raise ValueError("ShareSampler: one share per group")
        if any(s < 0 for s in shares) or abs(sum(shares) - 1.0) > 1e-6:
            raise ConfigError(f"shares {list(shares)}: each in [0, 1], summing to 1")
        for group, share in zip(groups, shares):
            if share > 0 and not group:
                raise ConfigError(f"a group with share {share:g} has no windows")
        self.groups = [torch.as_tensor(list(g), dtype=torch.int64) for g in groups]
        self.counts = share_counts(shares, int(length))

    def __len__(self) -> int:
        return sum(self.counts)

    def __iter__(self) -> Iterator[int]:
        seed = int(torch.empty((), dtype=torch.int64).random_().item())
        g = torch.Generator().manual_seed(seed)
        drawn = []
        for group, count in zip(self.groups, self.counts):
            passes = [group[torch.randperm(len(group), generator=g)] for _ in range(-(-count // max(1, len(group))))]
            drawn.append(torch.cat(passes)[:count] if passes else group[:0])
        order = torch.cat(drawn)
        return iter(order[torch.randperm(len(order), generator=g)].tolist())


def share_counts(shares: list[float], length: int) -> list[int]:
    """``length`` split by ``shares``: floors, then the largest remainders get one more each."""
    raw = [s * length for s in shares]
    counts = [int(r) for r in raw]
    for i in sorted(range(len(raw)), key=lambda i: counts[i] - raw[i])[: length - sum(counts)]:
        counts[i] += 1
    return counts


class SequenceShardSampler(DistributedSampler):
    """Validation/test items of :class:`~denoiser.data.dataset.SequenceDataset` for one DDP rank,
    sharded by *whole sequences*: every piece (``val_window``) of a sequence goes to the same rank,
    in order, so the recurrent state carried from piece to piece and tPSNR's frame-to-frame
    contiguity hold under DDP.

    Sequences are dealt out longest first to the rank with the fewest frames so far (ties: the
    lower rank), then each rank visits its pieces in dataset order. A rank left without a
    sequence (more ranks than sequences) re-runs the shortest one: its metrics are identical to
    the first copy's and :func:`denoiser.lit.common.gather_sequence_sums` keeps one copy per
    sequence name, so nothing is counted twice. Ranks may hold different numbers of batches;
    nothing in ``validation_step`` communicates, only the epoch end does (once per rank).

    A subclass of ``DistributedSampler`` so Lightning leaves it in place (it replaces only plain
    samplers when ``use_distributed_sampler`` is on, Lightning 2.x ``_requires_distributed_sampler``).
    """

    def __init__(self, pieces: list[tuple[int, int, int]], num_replicas: int = 1, rank: int = 0):
        if not 0 <= rank < num_replicas:
            raise ValueError(f"rank {rank} outside [0, {num_replicas})")
        self.num_replicas = int(num_replicas)
        self.rank = int(rank)
        self.epoch = 0
        self.shuffle = False
        self.drop_last = False
        self.seed = 0
        frames: dict[int, int] = {}
        for seq, _, length in pieces:
            frames[seq] = frames.get(seq, 0) + length
        load = [0] * self.num_replicas
        owner: dict[int, int] = {}
        for seq in sorted(frames, key=lambda s: (-frames[s], s)):
            r = min(range(self.num_replicas), key=lambda i: (load[i], i))
            owner[seq] = r
            load[r] += frames[seq]
        mine = {s for s, r in owner.items() if r == self.rank}
        if not mine and frames:  # an idle rank would skip the epoch-end gather: re-run the shortest sequence
            mine = {min(frames, key=lambda s: (frames[s], s))}
        self.indices = [i for i, (seq, _, _) in enumerate(pieces) if seq in mine]
        self.num_samples = self.total_size = len(self.indices)

    @classmethod
    def for_current_process(cls, pieces: list[tuple[int, int, int]]) -> SequenceShardSampler:
        """The shard of this process (rank and world size of ``torch.distributed``; 1 process without it)."""
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            return cls(pieces, dist.get_world_size(), dist.get_rank())
        return cls(pieces)

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices)

    def __len__(self) -> int:
        return len(self.indices)
