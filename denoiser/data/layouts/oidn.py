"""Intel Open Image Denoise's training-data naming: one feature per file (``layout=oidn``).

::

    <root>/<split>/**/<image>_<version>.<feature>.exr
        version: <n> or <n>spp (samples per pixel: a noisy render), or ref | reference | gt | target
        feature: hdr (color), alb (albedo), nrm (normal), z (depth), ...
    e.g.  kitchen_0004spp.hdr.exr  kitchen_0004spp.alb.exr  kitchen_0004spp.nrm.exr  kitchen_ref.hdr.exr

The naming is the one OIDN's ``training/`` toolkit reads (its ``doc/training.md``: ``.+_([0-9]+(spp)?|ref|
reference|gt|target)\\.(hdr|ldr|sh1[xyz]|alb|nrm)\\.exr``; the files of one image's versions lie in
the same folder, in any folder structure under the split). An image's *versions* are its noisy renders
and its reference: an explicitly named one (``_ref`` ...), else, as OIDN does, the version with the
most samples when there are several. The noisy version read is ``spp`` (null: the one with the fewest
samples). Its ``hdr`` file is ``color``, its ``alb``/``nrm``/``z`` files ``albedo``/``normal``/``depth``;
the reference's ``hdr`` is ``reference`` (file roles ``hdr``, ``alb``, ..., ``ref.hdr``, ``ref.alb``:
``buffers.albedo.file=ref.alb`` reads the clean albedo, as OIDN's ``--clean_aux``). Channels are
names tried in order (``[[R, G, B], [X, Y, Z]]``): OIDN's files hold one feature in their first channels.

**Sequences and single images.** OIDN's images are single frames. An image whose name matches
``frame_pattern`` (default ``<sequence>_f<frame>``, e.g. ``corridor_f0007_0004spp.hdr.exr``) is frame
``<frame>`` of the sequence ``<sequence>`` (frames numbered without gaps, any first number); every other
image is a sequence of one frame. Buffers these files do not hold are filled with constants
(``fill``): ``motion`` is zero (no motion vectors: the history is not warped; on single images,
trained with ``data.window=1``, there is no history at all) and ``depth``, where there is no ``z``
file, is one constant (no depth cue). A sequence is named ``<sequence>`` (two folders of a split
holding the same name is an error naming both).
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from denoiser.data import exr
from denoiser.data.layouts.base import BufferSpec, Layout, SequenceSource, image_size
from denoiser.data.layouts.native import check_sizes
from denoiser.data.sequence import SequenceMeta
from denoiser.errors import ConfigError, UserError

#: ``<image>_<version>.<feature>.exr`` (OIDN's training naming)
NAME_RE = re.compile(r"^(?P<image>.+)_(?P<version>\d+(?:spp)?|ref|reference|gt|target)\.(?P<feature>[A-Za-z0-9]+)\.exr$",
                     re.IGNORECASE)
#: versions that name the reference explicitly
REFERENCE_NAMES = frozenset({"ref", "reference", "gt", "target"})
#: the prefix of a reference file's role (``ref.hdr``)
REF = "ref."


@dataclasses.dataclass
class _Sequence:
    """One sequence as found: its folder, and per frame number ``{version: {feature: path}}``."""

    folder: Path
    frames: dict[int, dict[str, dict[str, Path]]] = dataclasses.field(default_factory=dict)


def _spp(version: str) -> int | None:
    """Samples per pixel of a noisy version (``0004spp``, ``0004``), None for a reference name."""
    v = version.lower()
    return None if v in REFERENCE_NAMES else int(v.removesuffix("spp"))


def _specs(buffers: Mapping[str, object]) -> dict[str, BufferSpec]:
    """Buffer specs from ``{buffer: {file, channels, convert}}``; ``channels`` a list of names or a
    list of alternative lists, tried in order."""
    specs = {}
    for name, entry in buffers.items():
        if not isinstance(entry, Mapping) or "file" not in entry or not entry.get("channels"):
            raise UserError(f"layout oidn: buffer '{name}' needs 'file' (a feature: hdr, alb, ref.hdr, ...) and 'channels'")
        chans = [c if isinstance(c, str) else [str(x) for x in c] for c in entry["channels"]]
        alternatives = ((tuple(chans),) if all(isinstance(c, str) for c in chans)
                        else tuple(tuple([c] if isinstance(c, str) else c) for c in chans))
        convert = entry.get("convert")
        if convert is not None and not callable(convert):
            raise UserError(f"layout buffer '{name}': 'convert' must be callable (use _target_ with _partial_: true)")
        specs[str(name)] = BufferSpec(str(entry["file"]), alternatives, convert)
    return specs


class OidnLayout(Layout):
    """OIDN-named files (see the module docstring).

    ``buffers``: ``{buffer: {file: <role>, channels: [...]}}`` (roles: a feature of the noisy version,
    ``ref.<feature>`` of the reference); ``fill``: ``{buffer: [value per channel]}``, the constant a
    buffer takes in a sequence without its file (``motion: [0, 0]``, ``depth: [1]``); ``spp``: the noisy
    version read (null: the fewest samples); ``frame_pattern``: a regular expression with groups
    ``sequence`` and ``frame`` matched against an image's name (null: every image its own sequence).
    """

    name = "oidn"

    def __init__(self, buffers: Mapping[str, object], fill: Mapping[str, Sequence[float]] | None = None,
                 spp: int | None = None, frame_pattern: str | None = r"^(?P<sequence>.+)_f(?P<frame>\d+)$"):
        self.specs = _specs(buffers)
        if "color" not in self.specs:
            raise UserError("layout oidn: buffers has no 'color'")
        self.fill = {str(k): tuple(float(x) for x in v) for k, v in (fill or {}).items()}
        self.spp = None if spp is None else int(spp)
        try:
            self.frame_pattern = re.compile(frame_pattern) if frame_pattern else None
        except re.error as exc:
            raise ConfigError(f"layout.frame_pattern: {frame_pattern!r}: {exc}") from None
        if self.frame_pattern is not None and not {"sequence", "frame"} <= set(self.frame_pattern.groupindex):
            raise ConfigError(f"layout.frame_pattern: {frame_pattern!r} needs the groups (?P<sequence>...) and (?P<frame>...)")
        self._found: dict[Path, _Sequence] = {}

    # ----------------------------------------------------------------- finding sequences

    def _scan(self, folder: Path, recursive: bool) -> dict[Path, _Sequence]:
        """``{<folder of the files>/<sequence>: _Sequence}`` of the OIDN-named files under ``folder``."""
        found: dict[Path, _Sequence] = {}
        paths = folder.rglob("*.exr") if recursive else folder.glob("*.exr")
        for path in sorted(paths):
            if path.name.startswith(".") or any(p.startswith(".") for p in path.relative_to(folder).parts[:-1]):
                continue
            m = NAME_RE.match(path.name)
            if m is None:
                continue
            image, frame = m["image"], None
            f = self.frame_pattern.match(image) if self.frame_pattern is not None else None
            if f is not None:
                image, frame = f["sequence"], int(f["frame"])
            seq = found.setdefault(path.parent / image, _Sequence(path.parent))
            seq.frames.setdefault(frame, {}).setdefault(m["version"], {})[m["feature"].lower()] = path
        for key, seq in found.items():
            if None in seq.frames and len(seq.frames) > 1:
                raise UserError(f"{key}: '{key.name}' names both a single image and a sequence of frames in {seq.folder}")
        return found

    def list_sequences(self, split_dir: str | os.PathLike) -> list[Path]:
        split_dir = Path(split_dir)
        if not split_dir.is_dir():
            raise UserError(f"{split_dir}: split directory does not exist")
        found = self._scan(split_dir, recursive=True)
        names: dict[str, Path] = {}
        for key in found:
            if key.name in names:
                raise UserError(f"{key}: sequence '{key.name}' is also in {names[key.name].parent} "
                                "(sequence names must differ within a split)")
            names[key.name] = key
        self._found.update(found)
        return sorted(found, key=lambda p: p.name)

    def _lookup(self, path: Path) -> _Sequence:
        if path in self._found:
            return self._found[path]
        if path.is_dir():  # a folder holding one sequence (e.g. denoiser-denoise input=<folder>)
            found = self._scan(path, recursive=False)
            if len(found) != 1:
                raise UserError(f"{path}: {len(found)} OIDN-named images or sequences here "
                                f"({', '.join(sorted(p.name for p in found)) or 'no <name>_<spp>spp.hdr.exr'}); give one")
            return next(iter(found.values()))
        if path.parent.is_dir():
            found = self._scan(path.parent, recursive=False)
            if path in found:
                return found[path]
        raise UserError(f"{path}: no OIDN-named files <name>_<spp>spp.<feature>.exr of this sequence")

    # ----------------------------------------------------------------- one sequence

    def _versions(self, where: str, versions: Mapping[str, Mapping[str, Path]]) -> tuple[str, str | None]:
        """``(noisy version, reference version or None)`` of one frame."""
        noisy = sorted((v for v in versions if _spp(v) is not None), key=_spp)
        refs = [v for v in versions if _spp(v) is None]
        if len(refs) > 1:
            raise UserError(f"{where}: several references ({', '.join(sorted(refs))}); keep one")
        ref = refs[0] if refs else (noisy.pop() if len(noisy) > 1 else None)  # OIDN: the most samples
        if not noisy:
            raise UserError(f"{where}: no noisy version (<name>_<spp>spp.hdr.exr), only {', '.join(sorted(versions))}")
        if self.spp is None:
            return noisy[0], ref
        chosen = [v for v in noisy if _spp(v) == self.spp]
        if not chosen:
            raise UserError(f"{where}: no {self.spp}-spp version (layout.spp); there are "
                            f"{', '.join(str(_spp(v)) for v in noisy)}")
        return chosen[0], ref

    def open_sequence(self, directory, name=None) -> SequenceSource:
        path = Path(directory)
        seq = self._lookup(path)
        numbers = sorted(seq.frames, key=lambda n: -1 if n is None else n)
        if numbers != [None] and numbers != list(range(numbers[0], numbers[0] + len(numbers))):
            gaps = sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))
            raise UserError(f"{path}: frames {numbers[0]}..{numbers[-1]} miss {', '.join(map(str, gaps[:5]))} "
                            "(a sequence's frames are numbered without gaps)")
        files: dict[str, list[Path]] = {}
        spp = 0
        for i, n in enumerate(numbers):
            where = f"{seq.folder / path.name}" + ("" if n is None else f" frame {n}")
            noisy, ref = self._versions(where, seq.frames[n])
            roles = {**seq.frames[n][noisy], **({REF + f: p for f, p in seq.frames[n][ref].items()} if ref else {})}
            if i == 0:
                spp = _spp(noisy)
                files = {role: [] for role in roles}
            missing = sorted(set(files) - set(roles))
            if missing:
                raise UserError(f"{where}: no {', '.join(missing)} file (the first frame has one)")
            for role in files:
                files[role].append(roles[role])
        color_role = self.specs["color"].file
        if color_role not in files:
            raise UserError(f"{seq.folder / path.name}: no noisy color file (<name>_<spp>spp.{color_role}.exr)")
        buffers = tuple(b for b, spec in self.specs.items()
                        if spec.file in files and self.resolve(files[spec.file][0], b, exr.list_channels(files[spec.file][0])))
        buffers += tuple(b for b in self.fill if b not in buffers)
        width, height = image_size(files[color_role][0])
        for role, paths in files.items():
            check_sizes(paths, width, height, f"{files[color_role][0]} (the sequence's color)")
        meta = SequenceMeta(width=width, height=height, frames=len(numbers), spp=spp, buffers=buffers)
        return SequenceSource(name=name or path.name, directory=path, meta=meta,
                              files={role: tuple(p) for role, p in files.items()}, buffers=buffers)

    # ----------------------------------------------------------------- reading

    def _filled(self, source: SequenceSource | None, buffer: str) -> bool:
        spec = self.specs.get(buffer)
        return buffer in self.fill and (spec is None or (source is not None and spec.file not in source.files))

    def role_of(self, buffer: str) -> str:
        if buffer not in self.specs and buffer in self.fill:
            return self.specs["color"].file
        return super().role_of(buffer)

    def file_for(self, source: SequenceSource, index: int, buffer: str) -> Path:
        """The file holding ``buffer`` of frame ``index``; for a filled buffer, the frame's color file."""
        if self._filled(source, buffer):
            return source.files[self.specs["color"].file][index]
        return super().file_for(source, index, buffer)

    def spec_key(self, buffer: str) -> str:
        if buffer not in self.specs and buffer in self.fill:
            return f"fill|{','.join(map(str, self.fill[buffer]))}"
        return super().spec_key(buffer) + (f"|fill {self.fill[buffer]}" if buffer in self.fill else "")

    def read_file(self, path: Path, buffers: Sequence[str], sample_count: int = 0) -> tuple[dict[str, np.ndarray], int]:
        """Read ``buffers`` of one file (float32 ``[H, W, C]``); a buffer of :attr:`fill` that this file
        does not hold (another feature's file, as :meth:`file_for` gives for a filled one) is its constant."""
        m = NAME_RE.match(path.name)
        feature = m["feature"].lower() if m else ""
        filled = [b for b in buffers if b in self.fill and (b not in self.specs or
                                                             self.specs[b].file.removeprefix(REF) != feature)]
        read = [b for b in buffers if b not in filled]
        arrays, bad = super().read_file(path, read, sample_count) if read else ({}, 0)
        if filled:
            width, height = image_size(path)
            for b in filled:
                arrays[b] = np.broadcast_to(np.asarray(self.fill[b], np.float32), (height, width, len(self.fill[b]))).copy()
        return arrays, bad

    def available_buffers(self, path: Path) -> tuple[str, ...]:
        present: Iterable[str] = exr.list_channels(path)
        return tuple(b for b in self.specs if self.resolve(path, b, present) is not None) + tuple(self.fill)


__all__ = ["NAME_RE", "OidnLayout"]
