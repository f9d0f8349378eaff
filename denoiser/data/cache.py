"""Decoded-frame cache on disk: each EXR buffer is decoded once, later reads fetch only a crop.

Entry = one logical buffer of one file, stored as a float32 ``.npy`` array ``[C, H, W]``
(channel planes: a crop is ``C`` runs of contiguous rows, fetched with ``C`` plain file reads
by :meth:`FrameCache.read`, and becomes a tensor without a transpose; :meth:`FrameCache.load`
maps a whole entry). Float32, not float16: HDR radiance above 65504 would overflow half
precision, and values are never clamped on load (docs/design.md §3.2).

Key: SHA-1 of (absolute path, file size, modification time in ns, buffer name, layout spec
text). Changing or touching the EXR, or reading the buffer through different channels or a
different conversion, makes a new entry; stale entries are never read (delete the directory
to reclaim space). Entries live at ``<cache_dir>/<key[:2]>/<key>.npy``.

Writes are atomic (temporary file in the same directory, then ``os.replace``), so concurrent
DataLoader workers may race to fill the same entry safely. ``cache_dir: null`` in the data
config turns the cache off (every read decodes the EXR).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from denoiser.atomic import atomic_path


class FrameCache:
    """Memory-mapped float32 ``[C, H, W]`` buffers keyed by file identity and buffer spec."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)

    @staticmethod
    def identity(path: str | os.PathLike) -> str:
        """``"<absolute path>|<size>|<mtime ns>"`` of a file (changes when the file does)."""
        st = os.stat(path)
        return f"{os.path.abspath(path)}|{st.st_size}|{st.st_mtime_ns}"

    @staticmethod
    def digest(identity: str, buffer: str, spec: str) -> str:
        """Cache key of one buffer of one file (``identity`` from :meth:`identity`)."""
        return hashlib.sha1(f"{identity}|{buffer}|{spec}".encode()).hexdigest()

    @classmethod
    def key(cls, path: str | os.PathLike, buffer: str, spec: str) -> str:
        return cls.digest(cls.identity(path), buffer, spec)

    def entry(self, key: str) -> Path:
        return self.directory / key[:2] / f"{key}.npy"

    def load(self, key: str) -> np.ndarray | None:
        """The cached array as a read-only memory map ``[C, H, W]``, or None on a miss."""
        p = self.entry(key)
        try:
            return np.load(p, mmap_mode="r")
        except (FileNotFoundError, ValueError, OSError, EOFError):
            return None  # missing, or unreadable (treated as a miss and rewritten)

    def read(self, key: str, height: int, width: int, crop: tuple[int, int, int, int] | None = None
             ) -> np.ndarray | None:
        """Rows of the entry's planes: float32 ``[C, h, w]`` for ``crop = (top, left, h, w)``
        (or the whole ``[C, H, W]``), or None on a miss (missing, damaged or another size).

        Reads only the crop's rows of each plane with plain file reads (no memory map to set up,
        no header to parse beyond its length), which is what makes warm reads cheap.
        """
        p = self.entry(key)
        try:
            with open(p, "rb", buffering=0) as fh:
                head = fh.read(12)
                if head[:6] != b"\x93NUMPY":
                    return None
                if head[6] == 1:
                    offset = 10 + int.from_bytes(head[8:10], "little")
                else:
                    offset = 12 + int.from_bytes(head[8:12], "little")
                header = fh.read(offset - len(head))
                if b"'<f4'" not in head + header or b"'fortran_order': False" not in head + header:
                    return None
                plane = height * width * 4
                channels, rest = divmod(os.fstat(fh.fileno()).st_size - offset, plane)
                if rest or channels < 1:
                    return None
                top, left, h, w = crop if crop is not None else (0, 0, height, width)
                rows = np.empty((channels, h, width), np.float32)
                for c in range(channels):
                    fh.seek(offset + c * plane + top * width * 4)
                    if fh.readinto(memoryview(rows[c]).cast("B")) != h * width * 4:
                        return None
        except (FileNotFoundError, OSError):
            return None
        return rows if (left, w) == (0, width) else np.ascontiguousarray(rows[:, :, left:left + w])

    def store(self, key: str, planes: np.ndarray) -> None:
        """Write ``planes`` (float32 ``[C, H, W]``) atomically under ``key``."""
        p = self.entry(key)
        with atomic_path(p) as tmp, open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(planes, dtype=np.float32))
