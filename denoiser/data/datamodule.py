"""``SequenceDataModule``: the LightningDataModule of every training/evaluation command.

Built by Hydra from ``conf/data/*.yaml`` (``_target_``); keys mirror the constructor. Splits
live at ``<root>/<split>/<sequence>/`` in the configured layout, and at ``<extra>/<split>/<sequence>/``
for each of ``extra_roots`` that has the split (families rendered as their own dataset, joined
without a copy: :func:`~denoiser.data.dataset.index_split`). Loaders:

* ``train_dataloader``: :class:`~denoiser.data.dataset.WindowDataset` of ``train_split``
  (windows of ``window`` frames, ``stride`` apart, random ``crop``, ``augment``), shuffled,
  ``batch_size`` items; with ``use_unlabeled`` also windows of ``unlabeled_split`` mixed in at
  ``unlabeled_ratio`` (:class:`~denoiser.data.sampler.MixedSampler`); every item then has a
  ``reference`` (zeros when unlabeled) and ``labeled: bool[B]`` says which are real.
  ``extra_share`` (null: every labeled window alike) draws that share of the labeled windows from
  the sequences of ``extra_roots`` and the rest from ``root``'s, an epoch as many windows as the
  labeled split holds (:class:`~denoiser.data.sampler.ShareSampler`): the mix of a recipe that
  trains on both, a config key;
* ``val_dataloader`` / ``test_dataloader``: :class:`~denoiser.data.dataset.SequenceDataset`,
  whole frames in order, batch size 1; ``val_window: null`` gives one whole sequence per batch.
  Under DDP each rank gets whole sequences (all their pieces, in order):
  :class:`~denoiser.data.sampler.SequenceShardSampler`, which Lightning leaves in place.

Streaming: datasets hold only the index; ``num_workers``, ``persistent_workers`` and
``pin_memory`` go to every DataLoader, whose workers start with ``multiprocessing_context``
(null: the standard library's start method, see :func:`worker_context`); ``cache_dir`` (or null) enables the decoded-frame cache;
``precache: true`` fills it for all splits in ``prepare_data`` (with a progress bar).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Mapping, Sequence

import lightning as L
from torch.utils.data import ConcatDataset, DataLoader
from tqdm.auto import tqdm

from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import instantiate_config
from denoiser.data.augment import Augment
from denoiser.data.collate import collate_items
from denoiser.data.dataset import SequenceDataset, WindowDataset, extra_root_entries, index_split
from denoiser.data.layouts.base import Layout, SequenceSource
from denoiser.data.reader import FrameReader
from denoiser.data.sampler import MixedSampler, SequenceShardSampler, ShareSampler
from denoiser.errors import ConfigError


def worker_context(name: str | None = None):
    """The ``multiprocessing`` context that starts DataLoader workers: ``name`` (fork, spawn or
    forkserver), else the process's start method when it is one of the standard library's, else
    the platform's default. A job run by ``hydra/launcher=joblib`` lives in a loky worker whose
    start method is ``'loky'``; its processes cannot start DataLoader workers (AttributeError on
    ``Process.env``), so that one is never used."""
    if name:
        if name not in multiprocessing.get_all_start_methods():
            raise ConfigError(f"data.multiprocessing_context: {name!r} is not one of "
                              f"{', '.join(multiprocessing.get_all_start_methods())}")
        return multiprocessing.get_context(name)
    method = multiprocessing.get_start_method(allow_none=True)
    if method in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context(method)
    return multiprocessing.get_context(multiprocessing.get_all_start_methods()[0])


def _instantiate(obj, cls, key: str):
    """Accept an object of ``cls`` or a Hydra config for one (``_target_``); ``key`` names it in errors."""
    if obj is None or isinstance(obj, cls):
        return obj
    if isinstance(obj, Mapping):
        if "_target_" in obj:
            return instantiate_config(obj, key)
        if cls is Augment:
            return Augment(**dict(obj))
    raise ConfigError(f"{key}: expected a {cls.__name__} or its config, got {type(obj).__name__}")


class SequenceDataModule(L.LightningDataModule):
    """Sequences of ``root`` as Lightning dataloaders (see the module docstring for the keys)."""

    def __init__(
        self,
        root: str,
        layout: Layout | Mapping,
        extra_roots: Sequence = (),
        buffers: Sequence[str] = FRAME_INPUTS,
        samples: bool = False,
        window: int = 8,
        stride: int = 1,
        crop: int | Sequence[int] | None = 128,
        batch_size: int = 4,
        num_workers: int = 0,
        persistent_workers: bool = False,
        pin_memory: bool = False,
        multiprocessing_context: str | None = None,
        cache_dir: str | None = None,
        precache: bool = False,
        augment: Augment | Mapping | None = None,
        use_unlabeled: bool = False,
        unlabeled_ratio: float = 0.5,
        train_split: str = "train",
        val_split: str | None = "val",
        test_split: str | None = "test",
        unlabeled_split: str = "unlabeled",
        val_window: int | None = None,
        extra_share: float | None = None,
    ):
        super().__init__()
        if root is None:  # experiment=my_data leaves it to the user
            raise ConfigError("data.root: required, the dataset root (<root>/<split>/<sequence>/), e.g. data.root=<renders>")
        self.root = str(root)
        self.extra_roots = tuple(extra_roots or ())  # paths or {root, layout} (dataset.extra_root_entries)
        self._extra = tuple(extra_root_entries(self.extra_roots))  # layouts built once
        self._extra_dirs = tuple(r for r, _ in self._extra)
        self.layout = _instantiate(layout, Layout, "data.layout")
        self.buffers = tuple(buffers)
        self.samples = bool(samples)
        self.window = int(window)
        self.stride = int(stride)
        self.crop = crop
        self.batch_size = int(batch_size)
        self.num_workers = int(num_workers)
        self.persistent_workers = bool(persistent_workers) and self.num_workers > 0
        self.pin_memory = bool(pin_memory)
        self.multiprocessing_context = multiprocessing_context
        worker_context(multiprocessing_context)  # a bad name fails here, before any training
        self.cache_dir = str(cache_dir) if cache_dir else None
        self.precache = bool(precache)
        self.augment = _instantiate(augment, Augment, "data.augment")
        self.use_unlabeled = bool(use_unlabeled)
        self.unlabeled_ratio = float(unlabeled_ratio)
        self.splits = {"train": train_split, "val": val_split, "test": test_split, "unlabeled": unlabeled_split}
        self.val_window = val_window
        self.extra_share = None if extra_share is None else float(extra_share)
        if self.extra_share is not None and not (0.0 <= self.extra_share <= 1.0 and self.extra_roots):
            raise ConfigError(f"data.extra_share: {extra_share} needs data.extra_roots and a value in [0, 1]")
        if self.batch_size < 1:
            raise ConfigError(f"data.batch_size: must be >= 1, got {batch_size}")
        self.train_set: WindowDataset | None = None
        self.unlabeled_set: WindowDataset | None = None
        self.val_set: SequenceDataset | None = None
        self.test_set: SequenceDataset | None = None

    # ------------------------------------------------------------------ datasets
    def _windows(self, split: str, labeled: bool) -> WindowDataset:
        sources = self._index(split)
        sizes = sorted({(s.width, s.height) for s in sources})
        if self.crop is None and self.batch_size > 1 and len(sizes) > 1:
            raise ConfigError(f"data.crop: null (whole frames) with batch_size {self.batch_size} needs one frame "
                              f"size, but {self.root}/{split} has {', '.join(f'{w}x{h}' for w, h in sizes)}")
        return WindowDataset(sources, self.layout, self.buffers, self.window, stride=self.stride, crop=self.crop,
                             augment=self.augment, labeled=labeled, samples=self.samples,
                             cache_dir=self.cache_dir, fill_reference=self.use_unlabeled)

    def _sequences(self, split: str) -> SequenceDataset:
        sources = self._index(split)
        return SequenceDataset(sources, self.layout, self.buffers, window=self.val_window, labeled=True,
                               samples=self.samples, cache_dir=self.cache_dir)

    def sequences(self, split: str) -> list[SequenceSource]:
        """The sequences of ``split`` (``train``/``val``/``test``/``unlabeled`` or a folder name),
        with their metadata (``source.meta``: scene, effects, cameras, render_seconds, ...)."""
        return self._index(self.splits.get(split) or split)

    def _index(self, split: str) -> list[SequenceSource]:
        return index_split(self.layout, self.root, split, self._extra)

    def prepare_data(self) -> None:
        if self.precache and self.cache_dir:
            self.fill_cache()

    def fill_cache(self) -> int:
        """Decode every frame of every configured split into the cache (progress bar); files decoded."""
        reader = FrameReader(self.layout, self.cache_dir)
        names = [self.splits[k] for k in ("train", "val", "test") if self.splits[k]]
        if self.use_unlabeled:
            names.append(self.splits["unlabeled"])
        jobs = []
        for split in names:
            if not os.path.isdir(os.path.join(self.root, split)):
                continue
            for src in self._index(split):
                wanted = [b for b in (*self.buffers, "reference", "samples") if b in src.buffers]
                jobs.extend((src, i, wanted) for i in range(src.frames))
        for src, i, wanted in tqdm(jobs, desc="cache frames", unit="frame"):
            reader.read(src, i, wanted, crop=(0, 0, 1, 1))
        return reader.decoded

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train_set is None:
            self.train_set = self._windows(self.splits["train"], labeled=True)
            if self.use_unlabeled:
                self.unlabeled_set = self._windows(self.splits["unlabeled"], labeled=False)
        if stage in (None, "fit", "validate") and self.val_set is None and self.splits["val"]:
            self.val_set = self._sequences(self.splits["val"])
        if stage in (None, "test", "predict") and self.test_set is None and self.splits["test"]:
            self.test_set = self._sequences(self.splits["test"])

    # ------------------------------------------------------------------ loaders
    def _loader(self, dataset, batch_size: int, shuffle: bool = False, sampler=None) -> DataLoader:
        return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, sampler=sampler,
                          num_workers=self.num_workers, persistent_workers=self.persistent_workers,
                          pin_memory=self.pin_memory, collate_fn=collate_items,
                          multiprocessing_context=worker_context(self.multiprocessing_context)
                          if self.num_workers > 0 else None)

    def extra_windows(self) -> list[bool]:
        """Per labeled training window: whether its sequence lies under one of ``extra_roots``."""
        if self.train_set is None:
            self.setup("fit")
        roots = [os.path.realpath(r) for r in self._extra_dirs]
        extra = [any(os.path.realpath(s.directory).startswith(r + os.sep) for r in roots) for s in self.train_set.sources]
        return [extra[i] for i, _ in self.train_set.windows]

    def train_dataloader(self) -> DataLoader:
        if self.train_set is None:
            self.setup("fit")
        if self.extra_share is not None:
            extra = self.extra_windows()
            n, u = len(self.train_set), (self.unlabeled_ratio if self.unlabeled_set is not None else 0.0)
            groups = [[i for i, e in enumerate(extra) if not e], [i for i, e in enumerate(extra) if e]]
            if self.extra_share > 0 and not groups[1]:
                raise ConfigError(f"data.extra_share={self.extra_share:g}: no {self.splits['train']} windows under "
                                  f"data.extra_roots ({', '.join(self._extra_dirs)}); render them (e.g. denoiser-render "
                                  "render_set=demo_motion) or train without them: data.extra_share=null data.extra_roots=[]")
            shares = [(1 - u) * (1 - self.extra_share), (1 - u) * self.extra_share]
            dataset = self.train_set
            if self.unlabeled_set is not None:
                dataset = ConcatDataset([self.train_set, self.unlabeled_set])
                groups.append(list(range(n, n + len(self.unlabeled_set))))
                shares.append(u)
            try:
                sampler = ShareSampler(groups, shares, round(n / (1 - u)))
            except ConfigError as exc:
                raise ConfigError(f"data.extra_share: {exc} (main root {len(groups[0])} windows, "
                                  f"extra_roots {len(groups[1])})") from None
            return self._loader(dataset, self.batch_size, sampler=sampler)
        if self.unlabeled_set is not None:
            mixed = ConcatDataset([self.train_set, self.unlabeled_set])
            sampler = MixedSampler(len(self.train_set), len(self.unlabeled_set), self.unlabeled_ratio)
            return self._loader(mixed, self.batch_size, sampler=sampler)
        return self._loader(self.train_set, self.batch_size, shuffle=True)

    def _sequence_loader(self, attr: str, stage: str) -> DataLoader | list:
        """Loader of whole sequences (or their pieces, in order) of the split held in ``attr``; under
        DDP each rank gets whole sequences (:class:`SequenceShardSampler`)."""
        if getattr(self, attr) is None:
            self.setup(stage)
        dataset = getattr(self, attr)
        if dataset is None:
            return []
        return self._loader(dataset, 1, sampler=SequenceShardSampler.for_current_process(dataset.pieces))

    def val_dataloader(self) -> DataLoader:
        return self._sequence_loader("val_set", "validate")

    def test_dataloader(self) -> DataLoader:
        return self._sequence_loader("test_set", "test")

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()
