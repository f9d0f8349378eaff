"""What every layout shares: buffer specs, the on-disk view of one sequence, frame reading.

A *layout* maps the logical buffers of docs/design.md §3.1 (``color``, ``albedo``, ``normal``,
``depth``, ``motion``, ``reference``, ``samples``) to files and EXR channel names. It is built
by Hydra from ``conf/layout/*.yaml`` (``_target_``) and answers three questions:

* which sequence directories a split holds (:meth:`Layout.list_sequences`);
* what one sequence holds (:meth:`Layout.open_sequence` -> :class:`SequenceSource`: metadata,
  one file per frame and *file role*, e.g. ``frame`` in the native layout, ``noisy`` and
  ``reference`` in the Blender layout);
* the pixels (:meth:`Layout.read_file` reads some buffers of one file; :meth:`Layout.read_frame`
  all requested buffers of one frame), as float32 ``[H, W, C]`` with NaN/Inf replaced.

A buffer spec lists *alternatives*: tuples of channel names tried in order (the first one
whose channels are all present wins), and an optional ``convert`` callable applied to the
assembled ``[H, W, C]`` array (the one place where a renderer's convention becomes ours).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from denoiser.buffers import sample_channels
from denoiser.data import exr
from denoiser.data.sequence import SequenceMeta
from denoiser.errors import ExrError, UserError

Converter = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class BufferSpec:
    """Where a logical buffer lives: file role, alternative channel-name tuples, conversion."""

    file: str
    alternatives: tuple[tuple[str, ...], ...]
    convert: Converter | None = None

    @property
    def num_channels(self) -> int:
        return len(self.alternatives[0])

    def key(self) -> str:
        """Stable text identifying this spec (part of the decoded-frame cache key)."""
        conv = ""
        if self.convert is not None:
            fn = getattr(self.convert, "func", self.convert)  # functools.partial from Hydra
            conv = f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', repr(fn))}"
        return f"{self.file}|{'/'.join(','.join(a) for a in self.alternatives)}|{conv}"


@dataclass(frozen=True)
class SequenceSource:
    """One sequence as found on disk.

    ``name``: ``<split>/<sequence>`` (or the directory name); ``files``: per file role, one path
    per frame (frame ``i`` of role ``r`` is ``files[r][i]``); ``buffers``: logical buffers
    available; ``sample_count``: per-sample radiance images per frame (0 if none); ``layout``: the
    layout that reads its files when it is not the dataset's (a sequence of an extra root in another
    layout, :func:`~denoiser.data.dataset.index_split`), else None.
    """

    name: str
    directory: Path
    meta: SequenceMeta
    files: Mapping[str, tuple[Path, ...]]
    buffers: tuple[str, ...]
    sample_count: int = 0
    extra: Mapping[str, object] = field(default_factory=dict)
    layout: Layout | None = None

    @property
    def frames(self) -> int:
        return self.meta.frames

    @property
    def width(self) -> int:
        return self.meta.width

    @property
    def height(self) -> int:
        return self.meta.height

    @property
    def cuts(self) -> tuple[int, ...]:
        return self.meta.cuts

    @property
    def labeled(self) -> bool:
        return "reference" in self.buffers


def parse_buffer_specs(buffers: Mapping[str, object], default_file: str) -> dict[str, BufferSpec]:
    """Build :class:`BufferSpec` s from a layout config's ``buffers`` mapping.

    Each entry is either a list of channel names, or a mapping with ``channels`` (names, or
    suffixes when ``passes`` is given), optional ``passes`` (alternative pass names, tried in
    order: channel ``<pass>.<suffix>``), optional ``file`` (role) and ``convert`` (callable).
    """
    specs: dict[str, BufferSpec] = {}
    for name, entry in buffers.items():
        if isinstance(entry, str) or not isinstance(entry, Mapping):
            entry = {"channels": entry}
        chans = entry.get("channels")
        if isinstance(chans, str) or not isinstance(chans, Sequence) or not chans:
            raise UserError(f"layout buffer '{name}': 'channels' must be a non-empty list of channel names")
        chans = tuple(str(c) for c in chans)
        passes = entry.get("passes")
        if passes:
            alternatives = tuple(tuple(f"{p}.{c}" for c in chans) for p in passes)
        else:
            alternatives = (chans,)
        convert = entry.get("convert")
        if convert is not None and not callable(convert):
            raise UserError(f"layout buffer '{name}': 'convert' must be callable (use _target_ with _partial_: true)")
        specs[str(name)] = BufferSpec(str(entry.get("file", default_file)), alternatives, convert)
    return specs


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an EXR file from its header (data window)."""
    header = exr.read_header(path)
    lo, hi = header["dataWindow"]
    return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


class Layout:
    """Base class: buffer specs plus reading; subclasses find sequences and their files."""

    #: name of the layout (``native``, ``blender``)
    name = "base"

    def __init__(self, buffers: Mapping[str, object], default_file: str):
        self.specs = parse_buffer_specs(buffers, default_file)

    # -- to be provided by subclasses
    def list_sequences(self, split_dir: str | os.PathLike) -> list[Path]:
        """Sequence directories of one split, sorted by name."""
        raise NotImplementedError

    def open_sequence(self, directory: str | os.PathLike, name: str | None = None) -> SequenceSource:
        """Index one sequence directory (validates metadata against the files)."""
        raise NotImplementedError

    # -- shared
    def resolve(self, path: Path, buffer: str, present: Iterable[str]) -> tuple[str, ...] | None:
        """Channel names of ``buffer`` in a file whose channels are ``present``; None if absent."""
        present = set(present)
        for alt in self.specs[buffer].alternatives:
            if all(c in present for c in alt):
                return alt
        return None

    def spec_key(self, buffer: str) -> str:
        """Text identifying how ``buffer`` is read (for the cache key)."""
        if buffer == "samples":
            return "samples|sample.k.RGB"
        return self.specs[buffer].key()

    def file_for(self, source: SequenceSource, index: int, buffer: str) -> Path:
        """The file holding ``buffer`` of frame ``index``."""
        role = self.role_of(buffer)
        if role not in source.files:
            raise UserError(f"{source.directory}: sequence has no '{role}' files (needed for buffer {buffer})")
        return source.files[role][index]

    def role_of(self, buffer: str) -> str:
        if buffer == "samples":
            return self.samples_role
        if buffer not in self.specs:
            raise UserError(f"layout {self.name}: unknown buffer '{buffer}'; known: {', '.join(self.specs)}")
        return self.specs[buffer].file

    samples_role = "frame"

    def read_file(self, path: Path, buffers: Sequence[str], sample_count: int = 0) -> tuple[dict[str, np.ndarray], int]:
        """Read ``buffers`` from one file: ``({buffer: float32 [H, W, C]}, nonfinite_count)``.

        ``samples`` comes back as ``[H, W, 3 * S]`` (sample-major: ``s*3 + c``) so every buffer
        is one ``[H, W, C]`` array. A missing buffer is an ``ExrError`` naming the file and the
        channels present.
        """
        present = exr.list_channels(path)
        wanted: dict[str, tuple[str, ...]] = {}
        for b in buffers:
            if b == "samples":
                wanted[b] = tuple(c for k in range(sample_count) for c in sample_channels(k))
                continue
            chans = self.resolve(path, b, present)
            if chans is None:
                tried = " or ".join(",".join(a) for a in self.specs[b].alternatives)
                raise ExrError(path, f"missing buffer {b} (channels {tried}); present: {', '.join(sorted(present))}")
            wanted[b] = chans
        arrays, bad = exr.read_frame(path, wanted)
        for b in buffers:
            spec = self.specs.get(b)
            if spec is not None and spec.convert is not None:
                arrays[b] = np.ascontiguousarray(spec.convert(arrays[b]), dtype=np.float32)
        return arrays, bad

    def read_frame(self, source: SequenceSource, index: int, buffers: Sequence[str]) -> tuple[dict[str, np.ndarray], dict[Path, int]]:
        """All ``buffers`` of frame ``index``: ``({buffer: float32 [H, W, C]}, {file: nonfinite_count})``."""
        by_file: dict[Path, list[str]] = {}
        for b in buffers:
            by_file.setdefault(self.file_for(source, index, b), []).append(b)
        out: dict[str, np.ndarray] = {}
        counts: dict[Path, int] = {}
        for path, bs in by_file.items():
            arrays, bad = self.read_file(path, bs, source.sample_count)
            out.update(arrays)
            counts[path] = bad
        return out, counts

    def available_buffers(self, path: Path) -> tuple[str, ...]:
        """Logical buffers of this layout resolvable in the file ``path`` (header only)."""
        present = exr.list_channels(path)
        return tuple(b for b in self.specs if self.resolve(path, b, present) is not None)
