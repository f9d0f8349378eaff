"""Frame reading for the datasets: layout decode, optional disk cache, crop, NaN/Inf report.

``FrameReader.read(source, index, buffers, crop)`` returns ``{buffer: float32 [C, h, w]}``
(channel planes; ``samples`` as ``[3*S, h, w]``). With a cache directory each buffer of each
file is decoded once (:mod:`denoiser.data.cache`) and later reads fetch only the crop's rows
from the cached float32 planes; without one (``cache_dir=None``) every read decodes the whole EXR.

NaN/Inf are replaced by the EXR reader (:func:`denoiser.data.exr.read_frame`); the count is
reported by one warning per file and process (logger ``denoiser.data.reader``) at decode
time. Cached data is already clean, so a file whose decode was cached is not reported again.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from denoiser.data.cache import FrameCache
from denoiser.data.layouts.base import Layout, SequenceSource

log = logging.getLogger(__name__)

#: ``(top, left, height, width)`` of a crop, in pixels.
Crop = tuple[int, int, int, int]


class FrameReader:
    """Reads buffers of frames through a layout, with an optional decoded-frame cache."""

    def __init__(self, layout: Layout, cache_dir: str | os.PathLike | None = None):
        self.layout = layout
        self.cache = FrameCache(cache_dir) if cache_dir else None
        self._reported: set[Path] = set()
        self.decoded = 0  #: files decoded by this reader (for tests and the benchmark)

    def _decode(self, path: Path, buffers: Sequence[str], source: SequenceSource) -> dict[str, np.ndarray]:
        arrays, bad = (source.layout or self.layout).read_file(path, buffers, source.sample_count)
        self.decoded += 1
        if bad and path not in self._reported:
            self._reported.add(path)
            log.warning("%s: replaced %d NaN/Inf value(s) (NaN, -Inf -> 0; +Inf -> 65504)", path, bad)
        return {b: a.transpose(2, 0, 1) for b, a in arrays.items()}

    def read(self, source: SequenceSource, index: int, buffers: Sequence[str],
             crop: Crop | None = None) -> dict[str, np.ndarray]:
        """Buffers of frame ``index``: ``{buffer: float32 [C, h, w]}`` (own memory, writable), read
        through the source's own layout when it has one (``source.layout``), else the reader's."""
        layout = source.layout or self.layout
        by_file: dict[Path, list[str]] = {}
        for b in buffers:
            by_file.setdefault(layout.file_for(source, index, b), []).append(b)
        sl = (slice(None),) if crop is None else (
            slice(None), slice(crop[0], crop[0] + crop[2]), slice(crop[1], crop[1] + crop[3]))
        out: dict[str, np.ndarray] = {}
        for path, bs in by_file.items():
            if self.cache is None:
                planes = self._decode(path, bs, source)
                for b in bs:
                    out[b] = np.ascontiguousarray(planes[b][sl], dtype=np.float32)
                continue
            ident = FrameCache.identity(path)
            keys = {b: FrameCache.digest(ident, b, layout.spec_key(b)) for b in bs}
            for b in bs:
                hit = self.cache.read(keys[b], source.height, source.width, crop)
                if hit is not None:
                    out[b] = hit
            missing = [b for b in bs if b not in out]
            if missing:
                planes = self._decode(path, missing, source)
                for b in missing:
                    self.cache.store(keys[b], planes[b])
                    out[b] = np.ascontiguousarray(planes[b][sl], dtype=np.float32)
        return out
