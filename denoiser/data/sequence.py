"""``sequence.json``: the metadata file of one rendered sequence (schema, loader, writer).

One file per sequence directory, next to its frames (docs/design.md §3.1)::

    <root>/<split>/<sequence>/sequence.json
    <root>/<split>/<sequence>/frame_0000.exr ...

The schema (``format_version`` 1) is documented field by field in ``docs/sequence_format.md``
and mirrored by :class:`SequenceMeta`. :func:`load_sequence_json` validates a file (missing or
mistyped fields, per-frame lists whose length disagrees with ``frames``, cuts out of range) and
raises a one-line :class:`~denoiser.errors.UserError` naming the file and the key;
:func:`check_frames_on_disk` compares it with the EXR files actually present (count and size).
:func:`write_sequence_json` writes one atomically (the simulator calls it).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from denoiser.atomic import atomic_write_text
from denoiser.buffers import REQUIRED_BUFFERS, SEQUENCE_BUFFERS
from denoiser.errors import UserError

FORMAT_VERSION = 1
SEQUENCE_JSON = "sequence.json"



@dataclass(frozen=True)
class Camera:
    """Camera of one frame.

    ``to_world``: 4x4 camera-to-world matrix as the renderer used it (row-major nested lists;
    Mitsuba: the camera looks along its local +z with +y up). ``fov``: field of view in degrees
    along ``fov_axis`` (``"x"`` by default, as in Mitsuba).
    """

    to_world: tuple[tuple[float, ...], ...]
    fov: float
    fov_axis: str = "x"

    def to_json(self) -> dict:
        return {"to_world": [list(r) for r in self.to_world], "fov": self.fov, "fov_axis": self.fov_axis}


@dataclass(frozen=True)
class SequenceMeta:
    """Contents of ``sequence.json`` (see ``docs/sequence_format.md``).

    ``cuts``: sorted frame indices where a new shot starts (history must reset there; frame 0
    always starts a shot and need not be listed). ``cameras``: one :class:`Camera` per frame,
    or empty when unknown (e.g. Blender renders without a ``sequence.json``).
    ``extra``: unknown top-level keys, kept so newer writers do not lose information.
    """

    width: int
    height: int
    frames: int
    spp: int
    buffers: tuple[str, ...]
    cameras: tuple[Camera, ...] = ()
    cuts: tuple[int, ...] = ()
    scene: Mapping[str, Any] = field(default_factory=lambda: {"name": "", "effects": []})
    renderer: Mapping[str, Any] = field(default_factory=lambda: {"name": "", "version": "", "variant": ""})
    seeds: Mapping[str, Any] = field(default_factory=dict)
    render_seconds: Mapping[str, float] = field(default_factory=dict)
    sample_count: int = 0
    format_version: int = FORMAT_VERSION
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def labeled(self) -> bool:
        """True when the sequence has a reference image."""
        return "reference" in self.buffers

    @property
    def scene_name(self) -> str:
        return str(self.scene.get("name", ""))

    def to_json(self) -> dict:
        """Plain JSON-ready dict with the documented key order."""
        out = {
            "format_version": self.format_version,
            "width": self.width,
            "height": self.height,
            "frames": self.frames,
            "spp": self.spp,
            "buffers": list(self.buffers),
            "sample_count": self.sample_count,
            "cameras": [c.to_json() for c in self.cameras],
            "cuts": list(self.cuts),
            "scene": dict(self.scene),
            "renderer": dict(self.renderer),
            "seeds": dict(self.seeds),
            "render_seconds": dict(self.render_seconds),
        }
        for k, v in self.extra.items():
            out.setdefault(k, v)
        return out


# ----------------------------------------------------------------------------- validation


class _Checker:
    """Field accessors that raise ``UserError("<file>: key <k>: problem")``."""

    def __init__(self, path: Path, data: Mapping[str, Any]):
        self.path = path
        self.data = data

    def fail(self, key: str, problem: str) -> UserError:
        return UserError(f"{self.path}: key '{key}': {problem}")

    def get(self, key: str, required: bool = True, default: Any = None) -> Any:
        if key not in self.data:
            if required:
                raise UserError(f"{self.path}: missing required key '{key}'")
            return default
        return self.data[key]

    def integer(self, key: str, minimum: int, required: bool = True, default: int = 0) -> int:
        v = self.get(key, required, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(key, f"must be an integer, got {v!r}")
        if v < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {v}")
        return v

    def mapping(self, key: str, required: bool = True) -> dict:
        v = self.get(key, required, {})
        if not isinstance(v, Mapping):
            raise self.fail(key, f"must be an object, got {type(v).__name__}")
        return dict(v)


def _parse_camera(chk: _Checker, i: int, cam: Any) -> Camera:
    key = f"cameras[{i}]"
    if not isinstance(cam, Mapping):
        raise chk.fail(key, "must be an object with to_world and fov")
    m = cam.get("to_world")
    ok = isinstance(m, Sequence) and len(m) == 4 and all(isinstance(r, Sequence) and len(r) == 4 for r in m)
    if not ok:
        raise chk.fail(f"{key}.to_world", "must be a 4x4 matrix (list of 4 rows of 4 numbers)")
    try:
        rows = tuple(tuple(float(x) for x in r) for r in m)
    except (TypeError, ValueError):
        raise chk.fail(f"{key}.to_world", "must contain numbers only") from None
    if not all(math.isfinite(x) for r in rows for x in r):
        raise chk.fail(f"{key}.to_world", "contains NaN/Inf")
    fov = cam.get("fov")
    if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov < 180:
        raise chk.fail(f"{key}.fov", f"must be degrees in (0, 180), got {fov!r}")
    axis = cam.get("fov_axis", "x")
    if axis not in ("x", "y", "diagonal", "smaller", "larger"):
        raise chk.fail(f"{key}.fov_axis", f"must be x, y, diagonal, smaller or larger, got {axis!r}")
    return Camera(rows, float(fov), axis)


def parse_sequence_meta(data: Mapping[str, Any], path: str | os.PathLike = SEQUENCE_JSON) -> SequenceMeta:
    """Validate a decoded ``sequence.json`` and build :class:`SequenceMeta` (errors name ``path``)."""
    path = Path(path)
    if not isinstance(data, Mapping):
        raise UserError(f"{path}: top level must be a JSON object")
    chk = _Checker(path, data)
    version = chk.integer("format_version", 1)
    if version > FORMAT_VERSION:
        raise chk.fail("format_version", f"{version} is newer than this reader ({FORMAT_VERSION})")
    width = chk.integer("width", 1)
    height = chk.integer("height", 1)
    frames = chk.integer("frames", 1)
    spp = chk.integer("spp", 1)

    buffers = chk.get("buffers")
    if not isinstance(buffers, list) or not all(isinstance(b, str) for b in buffers):
        raise chk.fail("buffers", "must be a list of buffer names")
    unknown = [b for b in buffers if b not in SEQUENCE_BUFFERS]
    if unknown:
        raise chk.fail("buffers", f"unknown buffer(s) {', '.join(unknown)}; known: {', '.join(SEQUENCE_BUFFERS)}")
    missing = [b for b in REQUIRED_BUFFERS if b not in buffers]
    if missing:
        raise chk.fail("buffers", f"must include {', '.join(missing)}")
    sample_count = chk.integer("sample_count", 0, required=False, default=0)
    if "samples" in buffers and sample_count < 1:
        raise chk.fail("sample_count", "must be >= 1 when buffers lists 'samples'")

    cams = chk.get("cameras")
    if not isinstance(cams, list):
        raise chk.fail("cameras", "must be a list (one entry per frame)")
    if len(cams) != frames:
        raise chk.fail("cameras", f"has {len(cams)} entries but frames is {frames}")
    cameras = tuple(_parse_camera(chk, i, c) for i, c in enumerate(cams))

    cuts = chk.get("cuts")
    if not isinstance(cuts, list) or not all(isinstance(c, int) and not isinstance(c, bool) for c in cuts):
        raise chk.fail("cuts", "must be a list of frame indices")
    bad = [c for c in cuts if not 0 <= c < frames]
    if bad:
        raise chk.fail("cuts", f"frame index {bad[0]} out of range 0..{frames - 1}")
    if sorted(set(cuts)) != list(cuts):
        raise chk.fail("cuts", "must be sorted and without duplicates")

    scene = chk.mapping("scene")
    if not isinstance(scene.get("name"), str) or not scene["name"]:
        raise chk.fail("scene.name", "must be a non-empty string")
    effects = scene.setdefault("effects", [])
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        raise chk.fail("scene.effects", "must be a list of strings")
    renderer = chk.mapping("renderer")
    for k in ("name", "version", "variant"):
        if not isinstance(renderer.get(k), str):
            raise chk.fail(f"renderer.{k}", "must be a string")
    seeds = chk.mapping("seeds")
    for k, v in seeds.items():
        vals = v if isinstance(v, list) else [v]
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in vals):
            raise chk.fail(f"seeds.{k}", "must be an integer or a list of integers")
    render_seconds = chk.mapping("render_seconds")
    for k, v in render_seconds.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise chk.fail(f"render_seconds.{k}", f"must be a non-negative number, got {v!r}")

    known = {f.name for f in dataclasses.fields(SequenceMeta)} - {"extra"}
    extra = {k: v for k, v in data.items() if k not in known}
    return SequenceMeta(
        width=width, height=height, frames=frames, spp=spp, buffers=tuple(buffers), cameras=cameras,
        cuts=tuple(cuts), scene=scene, renderer=renderer, seeds=seeds,
        render_seconds={k: float(v) for k, v in render_seconds.items()}, sample_count=sample_count,
        format_version=version, extra=extra,
    )


def load_sequence_json(path: str | os.PathLike) -> SequenceMeta:
    """Read and validate ``sequence.json`` (a file path, or the sequence directory)."""
    path = Path(path)
    if path.is_dir():
        path = path / SEQUENCE_JSON
    if not path.exists():
        raise UserError(f"{path}: file does not exist (every sequence needs a {SEQUENCE_JSON})")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read ({exc})") from None
    return parse_sequence_meta(data, path)


def check_frames_on_disk(meta: SequenceMeta, json_path: str | os.PathLike, frame_files: Sequence[Path],
                         sizes: Sequence[tuple[int, int]] | None = None) -> None:
    """Raise ``UserError`` naming ``json_path`` when the files on disk disagree with ``meta``.

    ``frame_files``: the frame files found (one per frame); ``sizes``: their ``(width, height)``.
    """
    if len(frame_files) != meta.frames:
        raise UserError(f"{json_path}: key 'frames' says {meta.frames} but {len(frame_files)} frame file(s) "
                        f"are on disk in {Path(json_path).parent}")
    for f, (w, h) in zip(frame_files, sizes or ()):
        if (w, h) != (meta.width, meta.height):
            raise UserError(f"{json_path}: size {meta.width}x{meta.height} disagrees with {f} ({w}x{h})")


# ----------------------------------------------------------------------------- writing


def _as_meta(meta: SequenceMeta | Mapping[str, Any], path: Path) -> SequenceMeta:
    if isinstance(meta, SequenceMeta):
        return parse_sequence_meta(meta.to_json(), path)  # validates what we are about to write
    data = dict(meta)
    data.setdefault("format_version", FORMAT_VERSION)
    return parse_sequence_meta(data, path)


def format_sequence_json(data: Mapping[str, Any]) -> str:
    """JSON text with one top-level key per line and one camera per line (diff-friendly)."""
    lines = []
    for k, v in data.items():
        if k == "cameras" and v:
            body = ",\n".join(f"    {json.dumps(c)}" for c in v)
            lines.append(f'  {json.dumps(k)}: [\n{body}\n  ]')
        else:
            lines.append(f"  {json.dumps(k)}: {json.dumps(v)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def write_sequence_json(path: str | os.PathLike, meta: SequenceMeta | Mapping[str, Any]) -> SequenceMeta:
    """Validate ``meta`` (a :class:`SequenceMeta` or a plain dict) and write it atomically.

    ``path`` is the ``sequence.json`` file or its sequence directory. A dict without
    ``format_version`` gets the current one. Returns the validated :class:`SequenceMeta`.
    Invalid metadata is a ``UserError`` and nothing is written.
    """
    path = Path(path)
    if path.is_dir() or path.suffix != ".json":
        path = path / SEQUENCE_JSON
    parsed = _as_meta(meta, path)
    text = format_sequence_json(parsed.to_json())
    atomic_write_text(path, text)
    return parsed
