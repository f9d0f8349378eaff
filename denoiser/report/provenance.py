"""What a report names as the code and the data it measured: the checkout's commit
(:func:`git_commit`, ``-dirty`` with uncommitted changes), a summary's ``- commit:`` line
(:func:`commit_line`) and the content hash of a split (:func:`tree_hash`, over
:func:`hash_bytes`). The evaluation's own record of them, ``evaluation.json``, and the test
ledger are :mod:`denoiser.report.ledger`.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path


def tree_hash(root: str | os.PathLike) -> str:
    """SHA-256 over the relative paths and bytes of every file under ``root`` (sorted): the
    content hash of a split, so a report names exactly the frames it was measured on."""
    digest = hashlib.sha256()
    root = Path(root)
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(root)).encode() + b"\0")
        hash_bytes(digest, path)
    return digest.hexdigest()


def hash_bytes(digest, path: str | os.PathLike) -> None:
    """Feed the bytes of the file at ``path`` to ``digest`` (a hashlib object), a MiB at a time."""
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)


def commit_line(evaluation: Mapping | None) -> str:
    """A summary's ``- commit:`` line (``scripts/readme_results.py`` copies it into the ``copied by``
    line that ``scripts/readme_check.py`` reads): the commit its evaluation ran at (``evaluation``:
    :func:`denoiser.report.ledger.read_provenance`), else, for an evaluation older than its
    ``evaluation.json``, this checkout's commit now, said so."""
    if evaluation is not None:
        return f"- commit: {evaluation['commit']} (the evaluation's)"
    return f"- commit: {git_commit()} (the summary's: the evaluation wrote no evaluation.json)"


#: tracked files the commands themselves write as they run (the test ledger's rows): not a change to the code
RUN_RECORDS = ("docs/results/test_ledger.csv",)


def git_commit() -> str:
    """The checkout's short commit (``-dirty`` with uncommitted changes to tracked files other than
    :data:`RUN_RECORDS`), or ``unknown`` outside a git checkout: what a report names as the code that
    wrote it (a pipeline's evaluation appends to the ledger; the bench after it ran the same code)."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ":(top)",
                                *(f":(top,exclude){p}" for p in RUN_RECORDS)], capture_output=True,
                               check=False, text=True).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
