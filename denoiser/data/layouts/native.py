"""The native layout (docs/design.md §3.1): one EXR per frame holding every buffer, plus sequence.json.

::

    <root>/<split>/<sequence>/sequence.json
    <root>/<split>/<sequence>/frame_0000.exr   # color.R/G/B, albedo.R/G/B, normal.X/Y/Z, depth.Z,
                                               # motion.X/Y, reference.R/G/B, sample.k.R/G/B

Opening a sequence validates ``sequence.json`` against the disk: frame count, every frame's
size (from its header) and, on the first frame, that the declared buffers' channels exist.
Errors are one-line :class:`~denoiser.errors.UserError` s naming the file.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping
from pathlib import Path

from denoiser.buffers import sample_channels
from denoiser.data import exr
from denoiser.data.layouts.base import Layout, SequenceSource, image_size
from denoiser.data.sequence import SEQUENCE_JSON, SequenceMeta, check_frames_on_disk, load_sequence_json
from denoiser.errors import ExrError, UserError

FRAME_RE = re.compile(r"^frame_(\d+)\.exr$")


def list_sequence_dirs(split_dir: str | os.PathLike) -> list[Path]:
    """Sub-directories of a split directory (hidden ones skipped), sorted by name."""
    split_dir = Path(split_dir)
    if not split_dir.is_dir():
        raise UserError(f"{split_dir}: split directory does not exist")
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and not p.name.startswith("."))


def count_samples(present) -> int:
    """Number of consecutive ``sample.k.R/G/B`` triples present, from k = 0."""
    present = set(present)
    k = 0
    while all(c in present for c in sample_channels(k)):
        k += 1
    return k


def derived_meta(files: list[Path], buffers: tuple[str, ...]) -> SequenceMeta:
    """Metadata for frames without a ``sequence.json`` (size from the first header, no cuts)."""
    width, height = image_size(files[0])
    return SequenceMeta(width=width, height=height, frames=len(files), spp=0, buffers=buffers)


def check_sizes(files: list[Path], width: int, height: int, what: str) -> None:
    """Every file must be ``width`` x ``height`` (header read only)."""
    for f in files:
        w, h = image_size(f)
        if (w, h) != (width, height):
            raise ExrError(f, f"is {w}x{h} but {what} is {width}x{height}")


class NativeLayout(Layout):
    """``frame_XXXX.exr`` files with native channel names and a ``sequence.json``.

    ``buffers``: logical buffer -> channel names (``conf/layout/native.yaml``); per-sample
    radiance ``samples`` is always ``sample.k.R/G/B`` for ``k < sample_count``.
    ``require_meta``: a directory without ``sequence.json`` is an error (datasets) or indexed
    from its files alone (``False``, e.g. for denoising a folder of frames).
    """

    name = "native"

    def __init__(self, buffers: Mapping[str, object], require_meta: bool = True):
        super().__init__(buffers, default_file="frame")
        self.require_meta = bool(require_meta)

    def list_sequences(self, split_dir):
        return list_sequence_dirs(split_dir)

    @staticmethod
    def frame_files(directory: Path) -> list[Path]:
        found = []
        for p in directory.iterdir():
            m = FRAME_RE.match(p.name)
            if m:
                found.append((int(m.group(1)), p))
        found.sort()
        for i, (n, p) in enumerate(found):
            if n != i:
                raise UserError(f"{directory}: frame files must be numbered frame_0000.exr, frame_0001.exr, ... "
                                f"without gaps; expected frame {i} but found {p.name}")
        return [p for _, p in found]

    def open_sequence(self, directory, name=None) -> SequenceSource:
        directory = Path(directory)
        if not directory.is_dir():
            raise UserError(f"{directory}: sequence directory does not exist")
        files = self.frame_files(directory)
        json_path = directory / SEQUENCE_JSON
        if json_path.exists() or self.require_meta:
            meta = load_sequence_json(json_path)
            check_frames_on_disk(meta, json_path, files)
        else:
            if not files:
                raise UserError(f"{directory}: no frame_XXXX.exr files")
            meta = None
        if meta is None:
            present = exr.list_channels(files[0])
            buffers = tuple(b for b in self.specs if self.resolve(files[0], b, present) is not None)
            samples = count_samples(present)
            if samples:
                buffers += ("samples",)
            meta = derived_meta(files, buffers)
            meta = dataclasses.replace(meta, sample_count=samples)
        check_sizes(files, meta.width, meta.height, f"{json_path} (width x height)")
        self._check_channels(files[0], meta)
        return SequenceSource(
            name=name or directory.name, directory=directory, meta=meta, files={"frame": tuple(files)},
            buffers=tuple(b for b in meta.buffers if b in self.specs or b == "samples"),
            sample_count=meta.sample_count if "samples" in meta.buffers else 0,
        )

    def _check_channels(self, path: Path, meta: SequenceMeta) -> None:
        present = exr.list_channels(path)
        for b in meta.buffers:
            if b == "samples":
                need = [c for k in range(meta.sample_count) for c in sample_channels(k)]
                missing = [c for c in need if c not in present]
            elif b in self.specs:
                missing = [] if self.resolve(path, b, present) else list(self.specs[b].alternatives[0])
            else:
                continue
            if missing:
                raise ExrError(path, f"sequence.json lists buffer {b} but channel(s) {', '.join(missing)} are "
                                     f"missing; present: {', '.join(sorted(present))}")
