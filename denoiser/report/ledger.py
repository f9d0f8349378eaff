"""The test ledger: every evaluation of a split named ``test`` is one row of a committed CSV, so
that a result can say how many times its split has been looked at, and which look it is.

A test split judges one frozen recipe once (docs/training.md, "Measuring honestly"); a split
looked at again is no longer unseen. ``denoiser-eval`` refuses ``split=test`` without a
``purpose=`` (for example ``final judgement of recipe X``, ``report``, ``debug``) and, after a
successful evaluation, appends one row to the ledger (``ledger=`` of ``conf/eval.yaml``; by
default :func:`default_ledger`: :data:`LEDGER` for the project's own datasets, a ``test_ledger.csv``
beside a user's data root for any other):

* ``date``: UTC, ``YYYY-MM-DDTHH:MM:SSZ``;
* ``dataset``: the data root; ``split``: the split's name; ``split_sha256``: the content hash of
  the split's files (:func:`denoiser.report.provenance.tree_hash`); ``split_id``: the split as drawn
  (:func:`split_id`: each sequence's metadata without its render timings, and its files' names), which
  identifies the split whatever its folder is called and however often it is rendered again;
* ``sequences``: how many sequences were evaluated (``sequences=`` may pick a subset);
* ``checkpoints``: the run ids (a checkpoint's run folder, else its file name), ``;``-separated;
  ``baselines``: the baseline methods, ``;``-separated;
* ``commit``: the code that evaluated (:func:`denoiser.report.provenance.git_commit`, ``-dirty``
  with uncommitted changes);
* ``purpose``: as given; ``look``: the how-many-th evaluation of this split the row is.

Looks are counted per ``split_id`` (a row from before that column, per ``split_sha256``): a split
copied to another folder keeps its count, the same sequences rendered again keep it too (a fresh
clone's ``make demo`` renders its test split anew: the render timings in each ``sequence.json``
differ, and so may a frame's Monte Carlo bytes), and a split drawn afresh (new seeds) starts at 1.
The metadata's floats count to :data:`FLOAT_DIGITS` significant digits: a camera matrix that numpy
computes on another CPU can differ in its last bits (an AVX-512 and an AVX2 render of the same
sequences gave two ids before 2026-12-02). Rows written before then hold the exact-float id, which
:func:`split_ids` also gives, so they keep counting where the same floats come out again.

Beside its tables, every evaluation writes :data:`PROVENANCE` (:func:`provenance`): the commit it
ran at, its date, the split and its hash, and for a test split the look it recorded. A summary takes
its commit from there, not from the checkout it runs in, and says which look its evaluation is of
how many the ledger holds now (:func:`looks_line`).
"""

from __future__ import annotations

import csv
import fcntl
import hashlib
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from denoiser.conf import CONF_DIR
from denoiser.errors import UserError
from denoiser.report.provenance import hash_bytes
from denoiser.tables import write_csv

ROOT = Path(__file__).resolve().parents[2]
#: the committed ledger of this checkout
LEDGER = ROOT / "docs" / "results" / "test_ledger.csv"
COLUMNS = ["date", "dataset", "split", "split_sha256", "split_id", "sequences", "checkpoints", "baselines", "commit",
           "purpose", "look"]
#: per-sequence metadata files: denoiser-render's sequence.json, scripts/blender_sequences.py's render.json
METADATA_FILES = ("sequence.json", "render.json")
#: their keys that time a render rather than define what it draws
VOLATILE_KEYS = ("render_seconds", "frame_seconds", "seconds")
#: significant digits of the metadata's floats in :func:`split_id` (None: exact, the ids before 2026-12-02)
FLOAT_DIGITS = 9
#: the split name whose evaluations are recorded (and need a purpose)
TEST_SPLIT = "test"
#: the evaluation's provenance, a JSON file beside its metrics.csv (denoiser-eval's out_dir)
PROVENANCE = "evaluation.json"
#: a user's ledger, beside their data root (:func:`default_ledger`)
LEDGER_NAME = "test_ledger.csv"
#: datasets the project renders besides its render sets, with scripts/blender_sequences.py: ``make blender``'s
#: (the Makefile's BLENDER_DATA) and ``make release``'s Cycles set (conf/pipeline/release.yaml's ``cycles``)
PROJECT_EXTRA_DATASETS = ("blender", "release_cycles")


def project_datasets() -> set[str]:
    """Names of the project's own datasets: each render set's ``name`` (``conf/render_set/*.yaml``,
    rendered by ``denoiser-render render_set=<name>`` into ``data/<name>``) and
    :data:`PROJECT_EXTRA_DATASETS`."""
    from omegaconf import OmegaConf

    names = set(PROJECT_EXTRA_DATASETS)
    for path in sorted(Path(CONF_DIR, "render_set").glob("*.yaml")):
        name = OmegaConf.load(path).get("name")
        if name:
            names.add(str(name))
    return names


def is_project_dataset(root: str | os.PathLike) -> bool:
    """Whether data root ``root`` is one of the project's own datasets: a folder named as one of
    :func:`project_datasets` directly in the checkout's ``data/`` or in ``$DENOISER_DATA`` (where the
    configs put them, ``${oc.env:DENOISER_DATA,data}/<name>``)."""
    path = Path(root).resolve()
    data_dirs = {(ROOT / "data").resolve(), Path(os.environ.get("DENOISER_DATA", ROOT / "data")).resolve()}
    return path.parent in data_dirs and path.name in project_datasets()


def default_ledger(root: str | os.PathLike) -> Path:
    """The ledger a look at a test split of data root ``root`` is recorded in when ``ledger=`` is not
    given: the project's tracked :data:`LEDGER` for its own datasets (:func:`is_project_dataset`),
    else ``<root>/test_ledger.csv``, the user's own, beside their splits (outside each split, so
    its hash is unchanged), which counts every look at their data whatever ``out_dir`` is."""
    return LEDGER if is_project_dataset(root) else Path(root) / LEDGER_NAME


def utc_now() -> str:
    """The UTC date and time as the ledger writes it, ``YYYY-MM-DDTHH:MM:SSZ``."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def is_test_split(split: str) -> bool:
    """Whether evaluating ``split`` is a look at a test split (its last path part is ``test``)."""
    return Path(str(split)).name == TEST_SPLIT


def run_id(checkpoint: str | os.PathLike) -> str:
    """A checkpoint's run id: the run folder of ``<run>/checkpoints/<file>.ckpt``, else the file's name."""
    path = Path(checkpoint)
    if path.parent.name == "checkpoints" and path.parent.parent.name:
        return path.parent.parent.name
    return path.name


def _rounded(value, digits: int):
    """``value`` (JSON data) with every float to ``digits`` significant digits."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v, digits) for v in value]
    return value


def split_id(root: str | os.PathLike, digits: int | None = FLOAT_DIGITS) -> str:
    """SHA-256 of the split under ``root`` as drawn: over its files in sorted order, a metadata file
    (:data:`METADATA_FILES`) by its relative path and its JSON without :data:`VOLATILE_KEYS` (keys
    sorted, floats to ``digits`` significant digits; None: exact), every other file in a folder that
    holds one by its relative path only (its bytes are one render of what the metadata draws), and a
    file elsewhere by its path and bytes (a split without metadata is its bytes, as
    :func:`denoiser.report.provenance.tree_hash`)."""
    return _split_digests(root, [digits])[0]


def split_ids(root: str | os.PathLike) -> list[str]:
    """The ids of the split under ``root`` a ledger row may hold: :func:`split_id`'s, then the
    exact-float one of the rows before 2026-12-02 (once when they are the same), in one pass over
    the files."""
    ids = _split_digests(root, [FLOAT_DIGITS, None])
    return ids[:1] if ids[0] == ids[1] else ids


class _Digests:
    """hashlib objects fed alike (a file's bytes read once for every id of :func:`_split_digests`)."""

    def __init__(self, n: int):
        self.all = [hashlib.sha256() for _ in range(n)]

    def update(self, data: bytes) -> None:
        for d in self.all:
            d.update(data)


def _split_digests(root: str | os.PathLike, digits: Sequence[int | None]) -> list[str]:
    """:func:`split_id` of ``root`` for each entry of ``digits``, in one walk of the split."""
    root = Path(root)
    files = sorted(p for p in root.rglob("*") if p.is_file())
    described = {p.parent for p in files if p.name in METADATA_FILES}
    digests = _Digests(len(digits))
    for path in files:
        digests.update(str(path.relative_to(root)).encode() + b"\0")
        if path.name in METADATA_FILES:
            try:
                meta = json.loads(path.read_text())
            except (OSError, ValueError):
                meta = None
            if isinstance(meta, dict):
                meta = {k: v for k, v in meta.items() if k not in VOLATILE_KEYS}
                for d, n in zip(digests.all, digits):
                    d.update(json.dumps(meta if n is None else _rounded(meta, n), sort_keys=True).encode() + b"\0")
                continue
        elif any(parent in described for parent in path.parents):
            continue
        hash_bytes(digests, path)
    return [d.hexdigest() for d in digests.all]


def _ids(split_id: str | Sequence[str] | None) -> list[str]:
    return [split_id] if isinstance(split_id, str) else [i for i in (split_id or []) if i]


def same_split(row: Mapping[str, str], split_sha256: str, split_id: str | Sequence[str] | None = None) -> bool:
    """Whether ledger ``row`` evaluated this split: by ``split_id`` (one id, or the ids of
    :func:`split_ids`) where both have one, else (a row or an evaluation from before that column)
    by the content hash."""
    ids = _ids(split_id)
    if ids and row.get("split_id"):
        return row["split_id"] in ids
    return row.get("split_sha256") == split_sha256


def read(ledger: str | os.PathLike = LEDGER) -> list[dict[str, str]]:
    """The ledger's rows as strings (no number parsing: hashes and commits stay text); [] when missing."""
    path = Path(ledger)
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def looks(split_sha256: str, ledger: str | os.PathLike = LEDGER, split_id: str | Sequence[str] | None = None) -> int:
    """How many rows of ``ledger`` evaluated this split (:func:`same_split`; 0 when there is no ledger).
    Without ``split_id`` (an evaluation from before that column), the draw that the ledger's rows of
    the same content hash name, when they name one."""
    rows = read(ledger)
    if not split_id:
        drawn = {row["split_id"] for row in rows if row.get("split_sha256") == split_sha256 and row.get("split_id")}
        split_id = drawn.pop() if len(drawn) == 1 else None
    return sum(1 for row in rows if same_split(row, split_sha256, split_id))


def record(dataset: str, split: str, split_sha256: str, sequences: int, checkpoints: Sequence[str],
           baselines: Sequence[str], commit: str, purpose: str, ledger: str | os.PathLike = LEDGER,
           date: str | None = None, split_id: str | Sequence[str] | None = None) -> int:
    """Append one evaluation to ``ledger`` (created with its header when missing; an exclusive lock
    on a side file keeps concurrent evaluations from losing a row; the write is atomic). Returns the
    look number of this row. ``date``: the row's (:func:`utc_now`, now when None); ``split_id``: the
    split as drawn (:func:`split_ids`: the row holds the first, earlier rows count under any)."""
    path = Path(ledger)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        rows: list[dict] = read(path)
        look = 1 + sum(1 for row in rows if same_split(row, split_sha256, split_id))
        rows.append({"date": date or utc_now(), "dataset": str(dataset),
                     "split": str(split), "split_sha256": split_sha256, "split_id": (_ids(split_id) or [""])[0],
                     "sequences": int(sequences),
                     "checkpoints": ";".join(checkpoints), "baselines": ";".join(baselines), "commit": commit,
                     "purpose": purpose, "look": look})
        write_csv(path, rows, COLUMNS)
    return look


def look_sentence(look: int, split_sha256: str, ledger: str | os.PathLike = LEDGER,
                  split_id: str | Sequence[str] | None = None) -> str:
    """One sentence for a report: which look this is, of how many recorded, naming the ledger."""
    total = looks(split_sha256, ledger, split_id)
    return (f"Test ledger: this evaluation is look {look} of {total} recorded at {split_sha256[:12]} "
            f"({Path(ledger).name}); a split looked at more than once is no longer unseen.")


def provenance(commit: str, date: str, dataset: str, split: str, split_sha256: str, sequences: int,
               look: int | None, ledger: str | os.PathLike | None,
               split_id: str | Sequence[str] | None = None) -> dict:
    """What :data:`PROVENANCE` holds: the commit the evaluation ran at (``-dirty`` with uncommitted
    changes), its UTC date, the data root, the split, its SHA-256, how many sequences, and for a
    test split the look it recorded and the ledger it recorded it in (None for another split); with
    ``split_id`` (:func:`split_ids`), the first as ``split_id`` and all as ``split_ids``."""
    told = {"commit": commit, "date": date, "dataset": str(dataset), "split": str(split), "split_sha256": split_sha256,
            "sequences": int(sequences), "look": look, "ledger": None if ledger is None else str(Path(ledger).resolve())}
    ids = _ids(split_id)
    if ids:
        told["split_id"], told["split_ids"] = ids[0], ids
    return told


def read_provenance(eval_dir: str | os.PathLike) -> dict | None:
    """The :data:`PROVENANCE` of an evaluation's ``out_dir``; None when there is none (an evaluation
    older than the file). UserError when it is not a JSON object."""
    path = Path(eval_dir) / PROVENANCE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not readable as JSON ({exc})") from None
    if not isinstance(data, dict) or not data.get("commit"):
        raise UserError(f"{path}: not an evaluation's provenance (no commit)")
    return data


def named(ledger: str | os.PathLike) -> str:
    """The ledger's path relative to the checkout when it lies in it (docs/results/test_ledger.csv)."""
    path = Path(ledger).resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def looks_line(evaluation: Mapping | None, ledger: str | os.PathLike = LEDGER) -> str:
    """One line for a summary's results block: how many times ``ledger`` has recorded the evaluated
    test split now, and which look ``evaluation`` (:func:`read_provenance`) was."""
    if evaluation is None:
        return "Test ledger: looks not recorded (evaluated before the ledger: no evaluation.json beside its metrics)."
    if evaluation.get("look") is None:
        return (f"Test ledger: looks not recorded (split `{evaluation.get('split')}` is not a test split; only a "
                f"split named {TEST_SPLIT} is).")
    digest, look = str(evaluation["split_sha256"]), int(evaluation["look"])
    total = looks(digest, ledger, evaluation.get("split_ids") or evaluation.get("split_id"))
    text = (f"Test ledger: this test split (SHA-256 {digest[:12]}) has been evaluated {total} "
            f"time{'' if total == 1 else 's'} ({named(ledger)}); this summary's evaluation is look {look}")
    if look > total:
        text += f" (recorded in another ledger: {evaluation.get('ledger')})"
    elif total > 1:
        text += "; a split looked at more than once is no longer unseen"
    return text + "."
