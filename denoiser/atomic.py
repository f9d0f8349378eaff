"""Atomic file writes: write under a temporary name beside the target, then rename.

A crash (even SIGKILL) never leaves a half-written file under its final name; at worst a hidden
``.<name>.*.tmp*`` file remains, which nothing reads and :func:`remove_stale_temporaries` removes
when the same command starts again (train: the run's ``checkpoints/``; eval: its output folder
and staging folders; denoise: its output folder). Used by every writer of the project (EXR
frames, ``sequence.json``, the frame cache, checkpoints, reports).
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "", fsync: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed to ``path``.

    suffix: extension of the temporary name (some writers pick the format from it); default
        the target's own suffix. fsync: flush the file to disk before the rename.
    On an exception the temporary file is removed and the target is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + (suffix or path.suffix), dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        if fsync:
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


#: Names :func:`atomic_path` (and FinalCheckpoint's ``.last.ckpt.tmp``) give temporary files:
#: hidden, ending in ``.tmp`` or ``.tmp<suffix>``.
_TEMPORARY = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9_]+)?$")


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file an atomic write leaves when it is killed mid-write."""
    return bool(_TEMPORARY.match(name))


def remove_stale_temporaries(directory: str | os.PathLike, partial_dirs: str | None = None) -> list[Path]:
    """Remove what killed atomic writes left in ``directory`` (not its subfolders): hidden
    ``.<name>.*.tmp*`` files, and, with ``partial_dirs`` (a glob such as ``.eval-*.partial``),
    staging folders whose name holds the id of a process that no longer runs. Returns what was
    removed. Called when a command starts, for its own output folder: two runs of one command
    writing into the same folder at the same time are not supported.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    removed = []
    for path in directory.iterdir():
        if path.is_file() and is_temporary(path.name):
            path.unlink(missing_ok=True)
            removed.append(path)
        elif partial_dirs and path.is_dir() and fnmatch.fnmatch(path.name, partial_dirs) and not _running(path.name):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _running(name: str) -> bool:
    """Whether the process whose id is the first number in ``name`` still runs (False without one)."""
    match = re.search(r"\d+", name)
    if not match:
        return False
    pid = int(match.group())
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def atomic_save_figure(fig, path: str | os.PathLike) -> Path:
    """Write a matplotlib figure to ``path`` as PNG, atomically (:func:`atomic_path`), and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)
