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
Every failure is an :class:`~denoiser.errors.ExrError` whose message names the file, and is one
line: deep images (deep scanline or deep tiled parts) are refused; a file any of whose parts
cannot be decoded fails as a whole (``OpenEXR.File`` itself only warns and drops such a part),
and so does a read during which the library reports an error even if pixels came back (e.g.
after rebuilding a damaged chunk table); what the library prints while reading (its C core on
file descriptor 2, its Python bindings on ``sys.stdout``) is captured into that message instead
of reaching the terminal (see :func:`library_output`); images and tiles wider or taller than
:data:`MAX_SIDE` are refused by the library's own header checks. ``tests/data/fuzz_exr.py`` fuzzes
the reader (docs/fuzzing.md).

HDR values are never clamped. ``read_frame`` replaces NaN/Inf by the project's one rule
(:mod:`denoiser.nonfinite`: NaN and -Inf by 0, +Inf by the largest finite float16 value, 65504,
which keeps "very bright" without overflowing anything downstream; the network applies the same
rule to its inputs) and returns how many values it replaced, so the caller can report it.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import OpenEXR

from denoiser.atomic import atomic_path
from denoiser.buffers import native_channels, sample_channels
from denoiser.errors import ExrError
from denoiser.nonfinite import POSINF, replace_array

EXR_MAGIC = b"\x76\x2f\x31\x01"

COMPRESSIONS: dict[str, object] = {
    name[: -len("_COMPRESSION")].lower(): getattr(OpenEXR, name)
    for name in dir(OpenEXR)
    if name.endswith("_COMPRESSION") and name != "NUM_COMPRESSION_METHODS"
}

#: Largest finite float16; +Inf is replaced by it on read (:data:`denoiser.nonfinite.POSINF`).
POS_INF_REPLACEMENT = POSINF

#: Largest image and tile side (pixels) accepted, by OpenEXR's own header checks (``Imf::Header::
#: setMaxImageSize`` / ``setMaxTileSize``), which this module sets at import unless they are set already
#: (they are process-wide; 0 = no limit, the library's default). Without them a 7 KB file whose header
#: declares 8 x 83886084 tiles made the library allocate ~24 GB and spend 80 s before failing (a finding
#: of tests/data/fuzz_exr.py).
MAX_SIDE = 16384
if OpenEXR.getMaxImageSize() == (0, 0):
    OpenEXR.setMaxImageSize(MAX_SIDE, MAX_SIDE)
if OpenEXR.getMaxTileSize() == (0, 0):
    OpenEXR.setMaxTileSize(MAX_SIDE, MAX_SIDE)

#: Part types this reader refuses (their pixels are per-pixel sample lists, not images).
DEEP_TYPES = (OpenEXR.deepscanline, OpenEXR.deeptile)
#: Longest library text kept in an error message.
MAX_DETAIL = 500

#: Lines the library prints when a read goes wrong: its core's error handler (``<file>: (EXR_ERR_<code>)
#: <message>``), the bindings' warning when they drop a part, the HTJ2K codec's errors.
LIBRARY_ERROR = re.compile(r"\(EXR_ERR_\w+\)|Exception raised reading|ojph error")

_OUTPUT_LOCK = threading.Lock()


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


@contextlib.contextmanager
def library_output() -> Iterator[list[str]]:
    """Capture what the OpenEXR library prints inside the block; yields a list that then holds the text.

    OpenEXR's C core reports damage with ``fprintf(stderr)`` (file descriptor 2) and the Python
    bindings ``print`` a warning to ``sys.stdout`` when they drop a part they cannot decode. File
    descriptor 2 is pointed at a temporary file for the block and restored after it (a
    ``sys.stderr`` swap would not see C writes), and ``sys.stdout`` is swapped for a buffer. Both
    are process-wide, so blocks are serialized by a lock: concurrent reads wait, each gets its own
    text. Output of other threads during the block is caught too; :func:`_open` passes on every
    line that is not one of the library's error reports (:data:`LIBRARY_ERROR`).
    """
    text: list[str] = []
    with _OUTPUT_LOCK, tempfile.TemporaryFile() as tmp:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(2)
        printed = io.StringIO()
        try:
            os.dup2(tmp.fileno(), 2)
            with contextlib.redirect_stdout(printed):
                yield text
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text.append(tmp.read().decode("utf-8", "replace") + printed.getvalue())


def _split_output(path: Path, text: list[str]) -> tuple[list[str], str]:
    """``(the library's error reports, one per line without the path they repeat; the rest of the text)``."""
    errors, rest = [], []
    for line in (text[0] if text else "").splitlines(keepends=True):
        if LIBRARY_ERROR.search(line):
            line = line.strip().removeprefix("Warning: ").removeprefix(f"{path}: ").strip()
            if line not in errors:
                errors.append(line)
        else:
            rest.append(line)
    return errors, "".join(rest)


def _detail(errors: list[str], exc: BaseException | None = None) -> str:
    """One line: the exception's text, then the library's error reports."""
    lines = [str(exc).strip().replace("\n", " ")] if exc is not None and str(exc).strip() else []
    lines += [e for e in errors if e not in lines]
    detail = "; ".join(lines) or (type(exc).__name__ if exc is not None else "no message from the library")
    return detail if len(detail) <= MAX_DETAIL else detail[: MAX_DETAIL - 3] + "..."


def _open(path: Path, header_only: bool = False) -> list[tuple[dict, dict[str, np.ndarray | None]]]:
    """The parts of a flat (not deep) EXR whose every part decodes: ``[(header, {channel: pixels})]``.

    The headers are read first (deep parts are refused before their samples are decoded), then,
    unless ``header_only`` (pixels None), the pixels; a part that ``OpenEXR.File`` dropped fails
    the read. Everything is converted to Python objects inside the capture (the bindings decode
    names and attributes lazily), so any failure is an ExrError naming ``path``.
    """
    _check_exr_file(path)
    error: BaseException | None = None
    deep = parts = None
    with library_output() as text:
        try:
            headers = OpenEXR.File(str(path), separate_channels=True, header_only=True)
            count = len(headers.parts)
            deep = next(((i, part.type()) for i, part in enumerate(headers.parts) if part.type() in DEEP_TYPES), None)
            if deep is None:
                f = headers if header_only else OpenEXR.File(str(path), separate_channels=True)
                parts = [(dict(part.header), {c.name: None for c in part.header.get("channels", [])} if header_only
                          else {name: ch.pixels for name, ch in part.channels.items()}) for part in f.parts]
                decoded = [part.name() for part, (_, chans) in zip(f.parts, parts) if header_only or chans]
                lost = [i for i, part in enumerate(headers.parts) if part.name() not in decoded] or [len(decoded)]
        except Exception as exc:  # noqa: BLE001 - OpenEXR raises plain RuntimeError/Exception on damage
            error = exc
    errors, rest = _split_output(path, text)
    if rest:  # not the library's: pass it on (another thread's output, say)
        sys.stderr.write(rest)
        sys.stderr.flush()
    if deep is not None:
        raise ExrError(path, f"deep EXR images are not supported (part {deep[0]} is {deep[1].name})")
    if error is not None or parts is None:
        raise ExrError(path, f"truncated or corrupt EXR ({_detail(errors, error)})") from None
    if not count or len(decoded) < count:
        where = "pixel data unreadable" if count <= 1 else f"part {lost[0]} of {count} unreadable"
        raise ExrError(path, f"truncated or corrupt EXR ({where}: {_detail(errors)})")
    if errors:  # pixels came back, but the library reported damage on the way (e.g. a rebuilt chunk table)
        raise ExrError(path, f"truncated or corrupt EXR ({_detail(errors)})")
    return parts


def list_channels(path: str | os.PathLike) -> list[str]:
    """All channel names of all parts of an EXR file (header only)."""
    names: list[str] = []
    for _, channels in _open(Path(path), header_only=True):
        names.extend(n for n in channels if n not in names)
    return names


def read_header(path: str | os.PathLike) -> dict:
    """Header of the first part (``dataWindow``, ``compression``, custom attributes)."""
    return _open(Path(path), header_only=True)[0][0]


def read_channels(path: str | os.PathLike, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Read channels (all, or the given names) as float32 ``[H, W]`` arrays.

    Channels are looked up in every part of a multi-part file. A missing requested channel is
    an :class:`ExrError` listing the channels that are present. Pixels are not sanitized here.
    """
    path = Path(path)
    found: dict[str, np.ndarray] = {}
    for _, channels in _open(path):
        for cname, pixels in channels.items():
            found.setdefault(cname, pixels)
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
        if not isinstance(arr, np.ndarray) or arr.ndim != 2:
            raise ExrError(path, f"channel {n} is not a 2-D image channel")
        out[n] = np.ascontiguousarray(arr, dtype=np.float32)
    return out


def sanitize(array: np.ndarray) -> int:
    """Replace NaN/-Inf by 0 and +Inf by 65504 in place (:mod:`denoiser.nonfinite`); return how many changed."""
    return replace_array(array)


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
