"""The test ledger: every evaluation of a split named ``test`` is one row of a committed CSV, so
that a result can say how many times its split has been looked at, and which look it is.

A test split judges one frozen recipe once (docs/training.md, "Measuring honestly"); a split
looked at again is no longer unseen. ``denoiser-eval`` refuses ``split=test`` without a
``purpose=`` (for example ``final judgement of recipe X``, ``report``, ``debug``) and, after a
successful evaluation, appends one row to the ledger (:data:`LEDGER`, or ``ledger=`` of
``conf/eval.yaml``):

* ``date``: UTC, ``YYYY-MM-DDTHH:MM:SSZ``;
* ``dataset``: the data root; ``split``: the split's name; ``split_sha256``: the content hash of
  the split's files (:func:`denoiser.report.summary.tree_hash`), which identifies the split
  whatever its folder is called;
* ``sequences``: how many sequences were evaluated (``sequences=`` may pick a subset);
* ``checkpoints``: the run ids (a checkpoint's run folder, else its file name), ``;``-separated;
  ``baselines``: the baseline methods, ``;``-separated;
* ``commit``: the code that evaluated (:func:`denoiser.report.summary.git_commit`, ``-dirty``
  with uncommitted changes);
* ``purpose``: as given; ``look``: the how-many-th evaluation of this ``split_sha256`` the row is.

Looks are counted per split hash: a split copied to another folder keeps its count, and a split
rendered afresh (new seeds) starts at 1.
"""

from __future__ import annotations

import csv
import fcntl
import os
import time
from collections.abc import Sequence
from pathlib import Path

from denoiser.measure import write_csv

ROOT = Path(__file__).resolve().parents[2]
#: the committed ledger of this checkout
LEDGER = ROOT / "docs" / "results" / "test_ledger.csv"
COLUMNS = ["date", "dataset", "split", "split_sha256", "sequences", "checkpoints", "baselines", "commit", "purpose",
           "look"]
#: the split name whose evaluations are recorded (and need a purpose)
TEST_SPLIT = "test"


def is_test_split(split: str) -> bool:
    """Whether evaluating ``split`` is a look at a test split (its last path part is ``test``)."""
    return Path(str(split)).name == TEST_SPLIT


def run_id(checkpoint: str | os.PathLike) -> str:
    """A checkpoint's run id: the run folder of ``<run>/checkpoints/<file>.ckpt``, else the file's name."""
    path = Path(checkpoint)
    if path.parent.name == "checkpoints" and path.parent.parent.name:
        return path.parent.parent.name
    return path.name


def read(ledger: str | os.PathLike = LEDGER) -> list[dict[str, str]]:
    """The ledger's rows as strings (no number parsing: hashes and commits stay text); [] when missing."""
    path = Path(ledger)
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def looks(split_sha256: str, ledger: str | os.PathLike = LEDGER) -> int:
    """How many rows of ``ledger`` evaluated the split of that hash (0 when there is no ledger)."""
    return sum(1 for row in read(ledger) if row.get("split_sha256") == split_sha256)


def record(dataset: str, split: str, split_sha256: str, sequences: int, checkpoints: Sequence[str],
           baselines: Sequence[str], commit: str, purpose: str, ledger: str | os.PathLike = LEDGER) -> int:
    """Append one evaluation to ``ledger`` (created with its header when missing; an exclusive lock
    on a side file keeps concurrent evaluations from losing a row; the write is atomic). Returns the
    look number of this row."""
    path = Path(ledger)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        rows: list[dict] = read(path)
        look = 1 + sum(1 for row in rows if row.get("split_sha256") == split_sha256)
        rows.append({"date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "dataset": str(dataset),
                     "split": str(split), "split_sha256": split_sha256, "sequences": int(sequences),
                     "checkpoints": ";".join(checkpoints), "baselines": ";".join(baselines), "commit": commit,
                     "purpose": purpose, "look": look})
        write_csv(path, rows, COLUMNS)
    return look


def look_sentence(look: int, split_sha256: str, ledger: str | os.PathLike = LEDGER) -> str:
    """One sentence for a report: which look this is, of how many recorded, naming the ledger."""
    total = looks(split_sha256, ledger)
    return (f"Test ledger: this evaluation is look {look} of {total} recorded at {split_sha256[:12]} "
            f"({Path(ledger).name}); a split looked at more than once is no longer unseen.")
