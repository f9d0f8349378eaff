"""EXR reading and writing on the OpenEXR 3.x Python API (``OpenEXR.File``).

Two levels:

* channels: ``read_channels(path) -> {channel_name: float32 [H, W]}`` (every part of a
  multi-part file is searched), ``write_channels(path, {name: [H, W]})``;
* buffers: ``write_frame(path, {"color": [H, W, 3], "depth": [H, W, 1], "samples": [S, H, W, 3]})``
  and ``read_frame(path, {"color": ("color.R", "color.G", "color.B"), ...})`` which assemble
  named multi-channel buffers ``[H, W, C]``.

Channel naming of the native layout (docs/design.md §3.1): buffer ``color`` is written as
``color.R/G/B``, ``normal`` as ``normal.X/Y/Z``, ``depth`` as ``depth.Z``, ``motion`` as
``motion.X/Y``; per-sample radiance ``samples`` ``[S, H, W, 3]`` as ``sample.<k>.R/G/B``.

Writes are atomic: the file is written under a temporary name in the same directory and
renamed into place, so a crash never leaves a half-written file under its final name.
Every failure is an :class:`~denoiser.errors.ExrError` whose message names the file.

HDR values are never clamped. ``read_frame`` replaces NaN/Inf (NaN and -Inf by 0, +Inf by
the largest finite float16 value, 65504, which keeps "very bright" without overflowing
anything downstream) and returns how many values it replaced, so the caller can report it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import OpenEXR

from denoiser.atomic import atomic_path
from denoiser.buffers import native_channels, sample_channels
from denoiser.errors import ExrError

EXR_MAGIC = b"\x76\x2f\x31\x01"

COMPRESSIONS: dict[str, object] = {
    name[: -len("_COMPRESSION")].lower(): getattr(OpenEXR, name)
    for name in dir(OpenEXR)
    if name.endswith("_COMPRESSION") and name != "NUM_COMPRESSION_METHODS"
}

#: Largest finite float16; +Inf is replaced by it on read.
POS_INF_REPLACEMENT = 65504.0


# ----------------------------------------------------------------------------- reading


def _check_exr_file(path: Path) -> None:
    if not path.exists():
        raise ExrError(path, "file does not exist")
    if path.is_dir():
        raise ExrError(path, "is a directory, not an EXR file")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise ExrError(path, f"cannot open ({exc.strerror})") from None
    if magic != EXR_MAGIC:
        raise ExrError(path, "not an EXR file (bad magic number)")


def _open(path: Path, header_only: bool = False) -> OpenEXR.File:
    _check_exr_file(path)
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as exc:  # noqa: BLE001 - OpenEXR raises plain RuntimeError/Exception on damage
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ExrError(path, f"truncated or corrupt EXR ({detail})") from None


def list_channels(path: str | os.PathLike) -> list[str]:
    """All channel names of all parts of an EXR file (header only)."""
    f = _open(Path(path), header_only=True)
    names: list[str] = []
    for part in f.parts:
        names.extend(n for n in _part_channel_names(part) if n not in names)
    return names


def _part_channel_names(part) -> list[str]:
    if part.channels:
        return list(part.channels.keys())
    return [c.name for c in part.header.get("channels", [])]


def read_header(path: str | os.PathLike) -> dict:
    """Header of the first part (``dataWindow``, ``compression``, custom attributes)."""
    f = _open(Path(path), header_only=True)
    return dict(f.parts[0].header)


def read_channels(path: str | os.PathLike, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Read channels (all, or the given names) as float32 ``[H, W]`` arrays.

    Channels are looked up in every part of a multi-part file. A missing requested channel is
    an :class:`ExrError` listing the channels that are present. Pixels are not sanitized here.
    """
    path = Path(path)
    f = _open(path)
    if not f.parts or not all(part.channels for part in f.parts):
        # OpenEXR.File only warns (on stderr) and drops the parts whose pixels cannot be read
        raise ExrError(path, "truncated or corrupt EXR (pixel data unreadable)")
    found: dict[str, np.ndarray] = {}
    try:
        for part in f.parts:
            for cname, ch in part.channels.items():
                if cname not in found:
                    found[cname] = ch.pixels
    except Exception as exc:  # noqa: BLE001 - any failure while decoding pixels means damage
        raise ExrError(path, f"truncated or corrupt EXR ({str(exc).strip() or type(exc).__name__})") from None
    if names is None:
        wanted = list(found)
    else:
        wanted = list(names)
        missing = [n for n in wanted if n not in found]
        if missing:
            raise ExrError(
                path,
                f"missing channel(s) {', '.join(missing)}; present: {', '.join(sorted(found)) or 'none'}",
            )
    out: dict[str, np.ndarray] = {}
    for n in wanted:
        arr = found[n]
        if arr is None or arr.ndim != 2:
            raise ExrError(path, f"channel {n} is not a 2-D image channel")
        out[n] = np.ascontiguousarray(arr, dtype=np.float32)
    return out


def sanitize(array: np.ndarray) -> int:
    """Replace NaN/-Inf by 0 and +Inf by 65504 in place; return how many values changed."""
    bad = ~np.isfinite(array)
    count = int(bad.sum())
    if count:
        np.copyto(array, np.where(np.isposinf(array), POS_INF_REPLACEMENT, 0.0).astype(array.dtype), where=bad)
    return count


def read_frame(
    path: str | os.PathLike,
    buffers: Mapping[str, Sequence[str]],
    optional: Iterable[str] = (),
) -> tuple[dict[str, np.ndarray], int]:
    """Read named buffers ``{buffer: channel names}`` into float32 ``[H, W, C]`` arrays.

    Buffers named in ``optional`` are skipped when any of their channels is absent; the others
    must exist (error lists the channels present). All buffers must share one size.
    Returns ``(buffers, nonfinite_count)``; NaN/Inf are already replaced (see :func:`sanitize`).
    """
    path = Path(path)
    optional = set(optional)
    present = None
    wanted: list[str] = []
    for name, chans in buffers.items():
        if name in optional:
            if present is None:
                present = set(list_channels(path))
            if not all(c in present for c in chans):
                continue
        wanted.extend(chans)
    channels = read_channels(path, wanted)
    out: dict[str, np.ndarray] = {}
    shape = None
    bad = 0
    for name, chans in buffers.items():
        if not all(c in channels for c in chans):
            continue
        planes = [channels[c] for c in chans]
        for c, p in zip(chans, planes):
            if shape is None:
                shape = p.shape
            elif p.shape != shape:
                raise ExrError(path, f"channel {c} is {p.shape[1]}x{p.shape[0]} but others are {shape[1]}x{shape[0]}")
        arr = np.stack(planes, axis=-1)
        bad += sanitize(arr)
        out[name] = arr
    return out, bad


def read_samples(path: str | os.PathLike, channels: Mapping[str, np.ndarray] | None = None) -> np.ndarray | None:
    """Per-sample radiance ``[S, H, W, 3]`` from ``sample.k.R/G/B`` channels, or None if absent."""
    names = channels.keys() if channels is not None else list_channels(path)
    ks = sorted({int(n.split(".")[1]) for n in names if n.startswith("sample.") and n.count(".") == 2
                 and n.split(".")[1].isdigit()})
    if not ks:
        return None
    wanted = [c for k in ks for c in sample_channels(k)]
    data = channels if channels is not None and all(c in channels for c in wanted) else read_channels(path, wanted)
    arr = np.stack([np.stack([data[c] for c in sample_channels(k)], axis=-1) for k in ks], axis=0)
    sanitize(arr)
    return arr.astype(np.float32, copy=False)


# ----------------------------------------------------------------------------- writing


def _atomic_write(path: Path, write) -> None:
    with atomic_path(path, suffix=".exr") as tmp:
        write(str(tmp))


def _compression(name: str):
    key = name.lower().replace("_compression", "")
    if key not in COMPRESSIONS:
        raise ExrError("<write>", f"unknown compression {name!r}; known: {', '.join(sorted(COMPRESSIONS))}")
    return COMPRESSIONS[key]


def write_channels(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    *,
    half: bool | Iterable[str] = False,
    compression: str = "zip",
    attributes: Mapping[str, object] | None = None,
) -> None:
    """Write ``{channel name: [H, W]}`` as a single-part scanline EXR, atomically.

    ``half=True`` stores every channel as float16; an iterable stores just those channels as
    float16; others are float32. ``attributes`` are extra header entries (strings, numbers).
    """
    path = Path(path)
    half_set = set(channels) if half is True else set(half or ())
    shape = None
    data: dict[str, np.ndarray] = {}
    for name, arr in channels.items():
        arr = np.asarray(arr)
        if arr.ndim != 2:
            raise ExrError(path, f"channel {name} must be 2-D [H, W], got shape {arr.shape}")
        if shape is None:
            shape = arr.shape
        elif arr.shape != shape:
            raise ExrError(path, f"channel {name} is {arr.shape[1]}x{arr.shape[0]} but others are {shape[1]}x{shape[0]}")
        dtype = np.float16 if name in half_set else np.float32
        data[name] = np.ascontiguousarray(arr, dtype=dtype)
    if not data:
        raise ExrError(path, "nothing to write (no channels)")
    header = {"compression": _compression(compression), "type": OpenEXR.scanlineimage}
    if attributes:
        header.update(dict(attributes))

    def write(tmp: str) -> None:
        with OpenEXR.File(header, data) as f:
            f.write(tmp)

    _atomic_write(path, write)


def write_frame(
    path: str | os.PathLike,
    buffers: Mapping[str, np.ndarray],
    *,
    half: bool | Iterable[str] = False,
    compression: str = "zip",
    channel_names: Mapping[str, Sequence[str]] | None = None,
    attributes: Mapping[str, object] | None = None,
) -> None:
    """Write named buffers as one EXR frame (native channel names unless given).

    ``buffers``: ``{name: [H, W, C] or [H, W]}``; the special buffer ``samples`` is
    ``[S, H, W, 3]`` and is written as ``sample.k.R/G/B``. ``half`` is True/False or an
    iterable of *buffer* names stored as float16.
    """
    half_buffers = set(buffers) if half is True else set(half or ())
    channels: dict[str, np.ndarray] = {}
    half_channels: list[str] = []
    for name, arr in buffers.items():
        arr = np.asarray(arr)
        if name == "samples":
            if arr.ndim != 4 or arr.shape[-1] != 3:
                raise ExrError(path, f"buffer samples must be [S, H, W, 3], got {arr.shape}")
            names = [sample_channels(k) for k in range(arr.shape[0])]
            for k, triple in enumerate(names):
                for c, cname in enumerate(triple):
                    channels[cname] = arr[k, :, :, c]
            if name in half_buffers:
                half_channels.extend(c for t in names for c in t)
            continue
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3:
            raise ExrError(path, f"buffer {name} must be [H, W, C], got shape {arr.shape}")
        names = tuple(channel_names[name]) if channel_names and name in channel_names else native_channels(
            name, arr.shape[-1])
        if len(names) != arr.shape[-1]:
            raise ExrError(path, f"buffer {name} has {arr.shape[-1]} channels but {len(names)} names")
        for c, cname in enumerate(names):
            channels[cname] = arr[:, :, c]
        if name in half_buffers:
            half_channels.extend(names)
    write_channels(path, channels, half=half_channels, compression=compression, attributes=attributes)


def write_multipart(path: str | os.PathLike, parts: Sequence[Mapping[str, np.ndarray]], *,
                    names: Sequence[str] | None = None, compression: str = "zip") -> None:
    """Write a multi-part EXR: one ``{channel: [H, W]}`` dict per part (used by tests and tools)."""
    path = Path(path)
    exr_parts = []
    first = np.asarray(next(iter(parts[0].values()))).shape
    # every part must share one display window; data windows follow each part's own size
    display = (np.array([0, 0], np.int32), np.array([first[1] - 1, first[0] - 1], np.int32))
    for i, chans in enumerate(parts):
        header = {"compression": _compression(compression), "type": OpenEXR.scanlineimage,
                  "name": (names[i] if names else f"part{i}"), "displayWindow": display}
        exr_parts.append(OpenEXR.Part(header, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in chans.items()}))

    def write(tmp: str) -> None:
        with OpenEXR.File(exr_parts) as f:
            f.write(tmp)

    _atomic_write(path, write)
