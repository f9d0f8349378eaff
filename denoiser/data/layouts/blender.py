"""Blender Cycles multilayer EXR renders, noisy and reference renders in separate folders.

::

    <root>/<split>/<sequence>/noisy/0001.exr, 0002.exr, ...      # low-spp render with passes
    <root>/<split>/<sequence>/reference/0001.exr, ...            # high-spp render (labeled splits)
    <root>/<split>/<sequence>/sequence.json                       # optional (cuts, cameras, spp)

A directory with the ``.exr`` files directly in it (no ``noisy/`` folder) is read as the noisy
frames of one unlabeled sequence (e.g. for ``denoiser-denoise layout=blender``). Noisy and
reference frames are paired by file name; frames are ordered by the number in the name.

Facts about Cycles files (docs/design.md §3.1; verified on Blender 5.0.1 renders, see
docs/sequence_format.md): float32 EXR, channels ``<ViewLayer>.<Pass>.<chan>``, the same names in
4.x and 5.0. Blender 5.0 writes one part per pass (part ``ViewLayer.<Pass>``) unless the output's
``use_exr_interleave`` is set (then a single part, as 4.x); :mod:`denoiser.data.exr` looks channels
up in every part, so both read alike. ``Combined.RGBA`` is the raw noisy image when Cycles'
denoiser is off; ``Noisy Image.RGBA`` exists only when the denoiser ran (and then ``Combined`` is
denoised), so the alias table of ``conf/layout/blender.yaml`` tries ``Noisy Image`` first for
``color``. ``Denoising Normal`` is camera space in our axes (x right, y up, z into the scene; 0 on
misses), ``Denoising Albedo`` is the albedo (above 1 on emitters). ``Depth.Z`` is planar depth
(no hit = 1e10); ``Denoising Depth.Z`` is the mean ray distance, 0 where nothing is hit, which
:func:`depth_misses_far` turns into 1e10.

Pass names are matched through the alias table with every prefix of ``layer_prefixes``
(default ``ViewLayer.`` and none); failing those, the single view layer of the file whose
channels complete the pass is used (several candidate layers are an error naming them).

**Motion conversion**: Blender's ``Vector`` pass stores in (X, Y) the position in frame
t-1 minus the position in frame t, in pixels, with +Y pointing *up*; (Z, W) are the position in
t minus the position in t+1 (verified on Blender 5.0.1 with a known camera and object motion).
Our ``motion`` (docs/design.md §3.1) is the same backward displacement with y pointing *down*, so
``motion = (X, -Y)``: :func:`vector_to_motion`, referenced from the layout config. The optional
buffer ``motion_next`` is (Z, W) converted the same way: ``(Z, -W)``, the position in t minus the
position in t+1, y down (earlier minus later, as ``motion``).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from denoiser.data import exr
from denoiser.data.layouts.base import Layout, SequenceSource, image_size, parse_buffer_specs
from denoiser.data.layouts.native import check_sizes, derived_meta, list_sequence_dirs
from denoiser.data.sequence import SEQUENCE_JSON, check_frames_on_disk, load_sequence_json
from denoiser.errors import ExrError, UserError

MISS_DEPTH = 1e10


def depth_misses_far(depth: np.ndarray) -> np.ndarray:
    """Depth ``[H, W, 1]`` with misses made far: values ``<= 0`` (or NaN) become ``1e10``.

    ``Depth.Z`` already stores 1e10 where a ray hits nothing; ``Denoising Depth.Z`` (the
    fallback when the Z pass is off) stores 0 there (verified on Blender 5.0.1), which our
    contract would read as "right at the camera". No hit can be at distance 0, so this is safe
    on both passes.
    """
    depth = np.array(depth, dtype=np.float32, copy=True)
    depth[~(depth > 0)] = MISS_DEPTH
    return depth


def vector_to_motion(vector: np.ndarray) -> np.ndarray:
    """Blender ``Vector`` (X, Y[, Z, W]) ``[H, W, >=2]`` -> our backward motion ``[H, W, 2]``.

    Blender: (X, Y) = pos(t-1) - pos(t) in pixels, +Y up. Ours: pos(t-1) - pos(t), y down.
    Hence ``motion = (X, -Y)``.
    """
    vector = np.asarray(vector, dtype=np.float32)
    motion = np.array(vector[..., :2], dtype=np.float32, copy=True)
    motion[..., 1] *= -1.0
    return motion


_NUM_RE = re.compile(r"(\d+)")


def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t for t in _NUM_RE.split(path.name)]


def exr_files(directory: Path) -> list[Path]:
    """``*.exr`` files of a directory (hidden/temporary ones skipped), in frame-number order."""
    return sorted((p for p in directory.iterdir() if p.suffix.lower() == ".exr" and not p.name.startswith(".")),
                  key=_natural_key)


class BlenderLayout(Layout):
    """Cycles multilayer EXRs; ``noisy_dir`` and ``reference_dir`` are sub-folder names.

    ``require_meta``: a directory without ``sequence.json`` is an error; by default (``False``)
    the file is optional (sizes from the frames, no cuts), as for ``NativeLayout(require_meta=False)``.
    ``optional_buffers``: buffers read where a file has them (same entries as ``buffers``) but never
    listed among a sequence's buffers nor required: ``motion_next``, the forward motion of
    the ``Vector`` pass that the flicker measure's forward-backward check reads
    (:mod:`denoiser.report.flicker`).
    """

    name = "blender"
    samples_role = "noisy"

    def __init__(self, buffers: Mapping[str, object], noisy_dir: str = "noisy", reference_dir: str = "reference",
                 layer_prefixes: Sequence[str] = ("ViewLayer.", ""), require_meta: bool = False,
                 optional_buffers: Mapping[str, object] | None = None):
        super().__init__(buffers, default_file="noisy")
        optional = parse_buffer_specs(optional_buffers or {}, "noisy")
        self.optional = frozenset(optional)
        self.specs.update(optional)
        self.noisy_dir = noisy_dir
        self.reference_dir = reference_dir
        self.layer_prefixes = tuple(layer_prefixes)
        self.require_meta = bool(require_meta)

    def list_sequences(self, split_dir):
        return list_sequence_dirs(split_dir)

    def resolve(self, path: Path, buffer: str, present: Iterable[str]) -> tuple[str, ...] | None:
        present = set(present)
        for alt in self.specs[buffer].alternatives:
            for prefix in self.layer_prefixes:
                names = tuple(prefix + c for c in alt)
                if all(n in present for n in names):
                    return names
            tail = "." + alt[0]
            layers = sorted({n[: -len(alt[0])] for n in present
                             if n.endswith(tail) and "." not in n[: -len(tail)]})
            layers = [p for p in layers if all(p + c in present for c in alt)]
            if len(layers) > 1:
                raise ExrError(path, f"buffer {buffer}: several view layers hold {alt[0].split('.')[0]} "
                                     f"({', '.join(p[:-1] for p in layers)}); set layout.layer_prefixes")
            if layers:
                return tuple(layers[0] + c for c in alt)
        return None

    def open_sequence(self, directory, name=None) -> SequenceSource:
        directory = Path(directory)
        if not directory.is_dir():
            raise UserError(f"{directory}: sequence directory does not exist")
        noisy_dir = directory / self.noisy_dir
        if not noisy_dir.is_dir():
            noisy_dir = directory
        noisy = exr_files(noisy_dir)
        if not noisy:
            raise UserError(f"{noisy_dir}: no .exr frames (expected Blender renders in {self.noisy_dir}/ or here)")
        files = {"noisy": tuple(noisy)}
        ref_dir = directory / self.reference_dir
        if ref_dir.is_dir():
            refs = {p.name: p for p in exr_files(ref_dir)}
            missing = [p.name for p in noisy if p.name not in refs]
            if missing:
                raise UserError(f"{ref_dir}: no reference frame for noisy frame(s) {', '.join(missing[:5])}")
            files["reference"] = tuple(refs[p.name] for p in noisy)

        buffers = self._buffers(files)
        json_path = directory / SEQUENCE_JSON
        if json_path.exists() or self.require_meta:
            meta = load_sequence_json(json_path)
            check_frames_on_disk(meta, json_path, noisy)
            meta = dataclasses.replace(meta, buffers=buffers)
        else:
            meta = derived_meta(noisy, buffers)
        for paths in files.values():
            check_sizes(list(paths), meta.width, meta.height, f"{directory} ({noisy[0].name})")
        return SequenceSource(name=name or directory.name, directory=directory, meta=meta, files=files,
                              buffers=buffers)

    def _buffers(self, files: Mapping[str, tuple[Path, ...]]) -> tuple[str, ...]:
        present = {role: exr.list_channels(paths[0]) for role, paths in files.items()}
        out = []
        for b, spec in self.specs.items():
            if b not in self.optional and spec.file in present and self.resolve(files[spec.file][0], b, present[spec.file]) is not None:
                out.append(b)
        if "color" not in out:
            path = files["noisy"][0]
            raise ExrError(path, f"no noisy color ({' or '.join(a[0] for a in self.specs['color'].alternatives)} "
                                 f"with a view-layer prefix); present: {', '.join(sorted(present['noisy']))}")
        return tuple(out)


__all__ = ["BlenderLayout", "depth_misses_far", "exr_files", "image_size", "vector_to_motion"]
