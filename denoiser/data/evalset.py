"""The labeled sequences that evaluation and the benchmark read, one frame at a time.

Frames stream from disk (memory does not grow with sequence length). A frame is
``{buffer: [1, C, H, W]}`` over :data:`denoiser.buffers.FRAME_INPUTS`, plus its reference
``[1, 3, H, W]`` and whether history resets there (the first frame and camera cuts). With
``open_test_split(..., samples=True)`` and a split whose sequences all hold per-sample radiance
(same count S), frames also carry ``samples [1, S, 3, H, W]`` (for methods that use them, ONND).
"""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from denoiser.buffers import FRAME_INPUTS
from denoiser.errors import UserError


def open_test_split(data_cfg: DictConfig, split: str, sequences=None, samples: bool = False):
    """``(layout, sources, dataset)`` for the labeled sequences of ``<data.root>/<split>`` (and of
    ``data.extra_roots``, :func:`~denoiser.data.dataset.index_split`).

    ``samples``: also read per-sample radiance, when every sequence has it with one count S
    (otherwise frames come without it, and a method that needs it says so)."""
    from denoiser.configs import instantiate_config
    from denoiser.data.dataset import SequenceDataset, index_split

    layout = instantiate_config(data_cfg.layout, "data.layout")
    sources = index_split(layout, data_cfg.root, split, data_cfg.get("extra_roots") or ())
    if sequences:
        wanted = [str(s) for s in sequences]
        by_name = {s.name.split("/", 1)[-1]: s for s in sources}
        missing = [w for w in wanted if w not in by_name and w not in {s.name for s in sources}]
        if missing:
            raise UserError(f"{Path(data_cfg.root) / split}: no sequence(s) {', '.join(missing)}; "
                            f"present: {', '.join(sorted(by_name))}")
        sources = [s for s in sources if s.name in wanted or s.name.split("/", 1)[-1] in wanted]
    unlabeled = [s for s in sources if not s.labeled]
    if unlabeled:
        raise UserError(f"{unlabeled[0].directory}: sequence has no reference buffer; evaluation needs "
                        "a labeled split")
    samples = bool(samples) and bool(sources) and all("samples" in s.buffers for s in sources) \
        and len({s.sample_count for s in sources}) == 1
    dataset = SequenceDataset(sources, layout, list(FRAME_INPUTS), window=1, labeled=True, samples=samples,
                              cache_dir=None)
    return layout, sources, dataset


def read_frame(dataset, source, index: int) -> tuple[dict, torch.Tensor, bool]:
    """Frame ``index`` of ``source``: ``(inputs {buffer: [1, C, H, W]}, reference [1, 3, H, W], reset)``
    (``inputs["samples"]`` ``[1, S, 3, H, W]`` too when the dataset reads them)."""
    item = dataset.load(source, index, 1, None)
    inputs = {b: item[b] for b in FRAME_INPUTS}
    if "samples" in item:
        inputs["samples"] = item["samples"]
    reset = index == 0 or index in source.cuts
    return inputs, item["reference"], reset


def sequence_reference(dataset, source, frames: int) -> torch.Tensor:
    """All reference frames ``[T, 3, H, W]`` of ``source`` (for the FLIP exposure range)."""
    return torch.stack([torch.from_numpy(dataset.reader.read(source, i, ["reference"])["reference"])
                        for i in range(frames)])
