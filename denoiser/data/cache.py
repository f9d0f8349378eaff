"""Decoded-frame cache on disk: each EXR buffer is decoded once, then read as a memory map.

Entry = one logical buffer of one file, stored as a float32 ``.npy`` array ``[C, H, W]``
(channel planes, so a crop is ``C`` runs of contiguous rows and becomes a tensor without a
transpose). Float32, not float16: HDR radiance above 65504 would overflow half precision and
values are never clamped on load (DESIGN 3.2).

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
import tempfile
from pathlib import Path

import numpy as np


class FrameCache:
    """Memory-mapped float32 ``[C, H, W]`` buffers keyed by file identity and buffer spec."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)

    @staticmethod
    def identity(path: str | os.PathLike) -> str:
        """``"<absolute path>|<size>|<mtime ns>"`` of a file (changes when the file does)."""
        st = os.stat(path)
        return f"{Path(path).resolve()}|{st.st_size}|{st.st_mtime_ns}"

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

    def store(self, key: str, planes: np.ndarray) -> None:
        """Write ``planes`` (float32 ``[C, H, W]``) atomically under ``key``."""
        p = self.entry(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=".tmp", dir=p.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.save(fh, np.ascontiguousarray(planes, dtype=np.float32))
            os.replace(tmp, p)
        except BaseException:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            raise
