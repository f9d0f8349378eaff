"""Sequence datasets: training windows (random crop + augmentation) and in-order evaluation.

Items are dicts (the batch contract of ``docs/contracts.md`` without the batch axis):

* ``color``, ``albedo``, ``reference``: float32 ``[T, 3, H, W]``; ``normal`` ``[T, 3, H, W]``;
  ``depth`` ``[T, 1, H, W]``; ``motion`` ``[T, 2, H, W]``; ``samples`` ``[T, S, 3, H, W]``;
* ``reset``: bool ``[T]``, True at the window's first frame and at every camera cut
  (``sequence.json`` ``cuts``) inside it, so a window never spans a cut without the flag;
* ``labeled``: bool scalar; ``sequence``: ``"<split>/<sequence>"``; ``frame_index``: int64 ``[T]``.

:class:`WindowDataset` (training): every run of ``window`` consecutive frames starting at a
multiple of ``stride``; the same random crop for all frames of a window, then
:class:`~denoiser.data.augment.Augment`. Unlabeled sequences carry no ``reference`` unless
``fill_reference`` (then zeros, with ``labeled=False``) so they collate with labeled ones.

:class:`SequenceDataset` (validation/test): whole frames, no augmentation, in order. With
``window=None`` one item is a whole sequence (``T`` = its frame count; ``reset`` True only at
frame 0 and at cuts); with ``window=k`` consecutive items are the k-frame pieces of a sequence
in order and ``reset`` is True only at the sequence start and cuts, so an evaluator running
with batch size 1 carries its state across items of one sequence.

Nothing is held in memory but the index (paths and metadata): frames stream from disk
through :class:`~denoiser.data.reader.FrameReader`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from denoiser.data.augment import Augment
from denoiser.data.layouts.base import Layout, SequenceSource
from denoiser.data.reader import Crop, FrameReader
from denoiser.errors import ConfigError, UserError

CHANNELS = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2, "reference": 3}


def extra_root_entries(extra_roots: Sequence) -> list[tuple[str, Layout | None]]:
    """``data.extra_roots`` as ``[(root, layout or None)]``. An entry is a root (a path: read in
    the dataset's layout) or ``{root: <path>, layout: <name or config>}``: a root in a layout of its
    own, e.g. Blender Cycles renders joined to Mitsuba ones, ``{root: data/release_cycles, layout:
    blender}`` (``layout``: a name of ``conf/layout/``, a ``_target_`` config or a Layout)."""
    from collections.abc import Mapping

    out: list[tuple[str, Layout | None]] = []
    for i, entry in enumerate(extra_roots or ()):
        if isinstance(entry, (str, os.PathLike)):
            out.append((str(entry), None))
            continue
        if isinstance(entry, tuple) and len(entry) == 2 and (entry[1] is None or isinstance(entry[1], Layout)):
            out.append((str(entry[0]), entry[1]))  # already parsed
            continue
        if not isinstance(entry, Mapping) or "root" not in entry or set(entry) - {"root", "layout"}:
            raise ConfigError(f"data.extra_roots[{i}]: a path or {{root: <path>, layout: <name>}}, got {entry!r}")
        layout = entry.get("layout")
        if isinstance(layout, str):
            from denoiser.configs import load_layout

            layout = load_layout(layout)
        elif isinstance(layout, Mapping):
            from denoiser.configs import instantiate_config

            layout = instantiate_config(layout, f"data.extra_roots[{i}].layout")
        elif layout is not None and not isinstance(layout, Layout):
            raise ConfigError(f"data.extra_roots[{i}].layout: a layout name or config, got {layout!r}")
        out.append((str(entry["root"]), layout))
    return out


def index_split(layout: Layout, root: str | os.PathLike, split: str,
                extra_roots: Sequence = ()) -> list[SequenceSource]:
    """Open every sequence of ``<root>/<split>`` (validated), names ``"<split>/<sequence>"``.

    ``extra_roots``: more dataset roots whose ``<extra>/<split>`` sequences join the split, when
    that folder exists (``data.extra_roots``: families rendered as their own dataset, e.g.
    ``conf/render_set/demo_motion.yaml``, added to another without copying it), each a path or
    ``{root, layout}`` (:func:`extra_root_entries`: a root in another layout, whose sources carry it
    as ``source.layout``). A sequence name in two roots is an error naming both folders."""
    import dataclasses

    found = [(d, None) for d in layout.list_sequences(os.path.join(root, split))]
    seen = {d.name: d for d, _ in found}
    for extra, own in extra_root_entries(extra_roots):
        folder = os.path.join(extra, split)
        if not os.path.isdir(folder):
            continue
        for d in (own or layout).list_sequences(folder):
            if d.name in seen:
                raise UserError(f"{d}: sequence {split}/{d.name} is also in {seen[d.name]} "
                                "(data.root and data.extra_roots must not share sequence names)")
            seen[d.name] = d
            found.append((d, own))
    sources = []
    for d, own in tqdm(found, desc=f"index {split}", unit="seq", leave=False, disable=len(found) < 50):
        src = (own or layout).open_sequence(d, name=f"{split}/{d.name}")
        sources.append(dataclasses.replace(src, layout=own) if own is not None else src)
    if not sources:
        raise UserError(f"{os.path.join(root, split)}: split has no sequences")
    return sources


def reset_flags(start: int, length: int, cuts: Sequence[int]) -> np.ndarray:
    """bool ``[length]``: True at the window start and where frame ``start+i`` begins a shot."""
    flags = np.zeros(length, dtype=bool)
    flags[0] = True
    for c in cuts:
        if start <= c < start + length:
            flags[c - start] = True
    return flags


def window_starts(frames: int, window: int, stride: int) -> range:
    """First frames of the ``window``-long runs of a ``frames``-long sequence, ``stride`` apart."""
    return range(0, max(frames - window + 1, 0), stride)


def parse_crop(crop) -> tuple[int, int] | None:
    """``crop``: null (whole frame), an int (square) or ``[height, width]``."""
    if crop is None:
        return None
    if isinstance(crop, int):
        crop = (crop, crop)
    h, w = (int(v) for v in crop)
    if h < 1 or w < 1:
        raise ConfigError(f"data.crop: must be positive, got {crop}")
    return h, w


def check_buffers(sources: Sequence[SequenceSource], wanted: Sequence[str]) -> None:
    for s in sources:
        missing = [b for b in wanted if b not in s.buffers]
        if missing:
            raise UserError(f"{s.directory}: sequence lacks buffer(s) {', '.join(missing)} "
                            f"(has {', '.join(s.buffers)})")


class _Frames(Dataset):
    """Shared loading of ``T`` frames of one sequence into the item dict."""

    def __init__(self, sources: Sequence[SequenceSource], layout: Layout, buffers: Sequence[str],
                 labeled: bool, samples: bool, cache_dir: str | os.PathLike | None, fill_reference: bool):
        self.sources = list(sources)
        self.buffers = [b for b in buffers if b not in ("reference", "samples")]
        if samples:
            self.buffers.append("samples")
        self.labeled = bool(labeled)
        if self.labeled:
            self.buffers.append("reference")
        self.fill_reference = bool(fill_reference)
        check_buffers(self.sources, self.buffers)
        counts = {s.sample_count for s in self.sources}
        if samples and len(counts) > 1:
            raise UserError(f"sequences of {self.sources[0].name.split('/')[0]} have different per-sample counts "
                            f"{sorted(counts)}; they cannot share a batch")
        self.reader = FrameReader(layout, cache_dir)

    def arrays(self, source: SequenceSource, start: int, length: int, crop: Crop | None) -> dict:
        """Frames ``start .. start+length-1`` of ``source`` as the item dict with numpy buffers.

        Buffers are float32 ``[T, C, h, w]`` (``samples`` ``[T, S, 3, h, w]``); ``reset``,
        ``labeled``, ``sequence`` and ``frame_index`` are already tensors / strings.
        """
        frames = [self.reader.read(source, start + i, self.buffers, crop) for i in range(length)]
        item: dict = {}
        for b in self.buffers:
            arr = np.stack([f[b] for f in frames])  # [T, C, h, w]
            if b == "samples":
                arr = arr.reshape(length, source.sample_count, 3, *arr.shape[-2:])
            item[b] = arr
        if not self.labeled and self.fill_reference:
            item["reference"] = np.zeros_like(item["color"])
        item["reset"] = torch.from_numpy(reset_flags(start, length, source.cuts))
        item["labeled"] = torch.tensor(self.labeled)
        item["sequence"] = source.name
        item["frame_index"] = torch.arange(start, start + length, dtype=torch.int64)
        return item

    @staticmethod
    def to_tensors(item: dict) -> dict:
        """Numpy buffers of an item -> contiguous float32 tensors (one copy at most)."""
        return {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) if isinstance(v, np.ndarray) else v
                for k, v in item.items()}

    def load(self, source: SequenceSource, start: int, length: int, crop: Crop | None) -> dict:
        """Frames ``start .. start+length-1`` of ``source``: the item dict (tensors ``[T, ...]``)."""
        return self.to_tensors(self.arrays(source, start, length, crop))


class WindowDataset(_Frames):
    """Training windows of ``window`` frames, random crop (same for all frames), augmentation.

    ``sources``: sequences of one split; ``buffers``: input buffers (``reference`` is added when
    ``labeled``, ``samples`` when ``samples``); ``crop``: int, ``[h, w]`` or None (whole
    frames); ``augment``: an :class:`Augment` or None; ``cache_dir``: decoded-frame cache or None.
    """

    def __init__(self, sources: Sequence[SequenceSource], layout: Layout, buffers: Sequence[str], window: int,
                 stride: int = 1, crop=None, augment: Augment | None = None, labeled: bool = True,
                 samples: bool = False, cache_dir: str | os.PathLike | None = None, fill_reference: bool = False):
        super().__init__(sources, layout, buffers, labeled, samples, cache_dir, fill_reference)
        if window < 1 or stride < 1:
            raise ConfigError(f"data.window and data.stride must be >= 1, got {window} and {stride}")
        self.window = int(window)
        self.crop = parse_crop(crop)
        self.augment = augment
        for s in self.sources:
            if self.crop and (self.crop[0] > s.height or self.crop[1] > s.width):
                raise UserError(f"{s.directory}: frames are {s.width}x{s.height}, smaller than data.crop "
                                f"{self.crop[1]}x{self.crop[0]}")
        self.windows = [(i, t) for i, s in enumerate(self.sources) for t in window_starts(s.frames, window, stride)]
        if not self.windows:
            longest = max(s.frames for s in self.sources)
            raise UserError(f"{self.sources[0].directory.parent}: no sequence has data.window={window} frames "
                            f"(longest has {longest})")

    def __len__(self) -> int:
        return len(self.windows)

    def random_crop(self, source: SequenceSource) -> Crop | None:
        if self.crop is None:
            return None
        h, w = self.crop
        top = int(torch.randint(0, source.height - h + 1, ()))
        left = int(torch.randint(0, source.width - w + 1, ()))
        return top, left, h, w

    def __getitem__(self, index: int) -> dict:
        seq, start = self.windows[index]
        source = self.sources[seq]
        item = self.arrays(source, start, self.window, self.random_crop(source))
        if self.augment is not None:
            item = self.augment(item)  # numpy views where possible; one copy below
        return self.to_tensors(item)


class SequenceDataset(_Frames):
    """Whole frames in order for validation/test; ``window=None``: one item per sequence."""

    def __init__(self, sources: Sequence[SequenceSource], layout: Layout, buffers: Sequence[str],
                 window: int | None = None, labeled: bool = True, samples: bool = False,
                 cache_dir: str | os.PathLike | None = None):
        super().__init__(sources, layout, buffers, labeled, samples, cache_dir, fill_reference=False)
        if window is not None and window < 1:
            raise ConfigError(f"data.val_window must be null or >= 1, got {window}")
        self.pieces: list[tuple[int, int, int]] = []
        for i, s in enumerate(self.sources):
            step = s.frames if window is None else int(window)
            self.pieces.extend((i, t, min(step, s.frames - t)) for t in range(0, s.frames, step))

    def __len__(self) -> int:
        return len(self.pieces)

    def __getitem__(self, index: int) -> dict:
        seq, start, length = self.pieces[index]
        source = self.sources[seq]
        item = self.load(source, start, length, None)
        if start > 0:  # a continuation: history carries over unless a cut starts this piece
            item["reset"][0] = start in source.cuts
        return item
