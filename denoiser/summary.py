"""Seed groups of an evaluation: per-method means and mean ± std over training seeds.

``denoiser-eval`` writes one row per method and sequence (``metrics.csv``: ``method, scene,
sequence, frames, psnr, ssim, tpsnr, flip, relmse, smape, ...``). A method trained with several
seeds appears once per seed, labelled ``<group>_s<seed>`` (e.g. ``student_distilled_s0``).
:func:`method_means` reduces the rows to one value per method and metric (the mean over
sequences of the per-sequence means, as the evaluation's own "Overall" table);
:func:`seed_groups` then gathers ``<group>_s<k>`` methods into one row with the mean and the
sample standard deviation over seeds (std 0 for a single run), in first-appearance order.
"""

from __future__ import annotations

import hashlib
import os
import re
import statistics
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

#: metrics summarised, with their Markdown headers (↑ higher is better, ↓ lower is better)
METRICS = {"psnr": "PSNR dB ↑", "ssim": "SSIM ↑", "tpsnr": "tPSNR dB ↑", "flip": "FLIP ↓", "relmse": "relMSE ↓"}
#: metrics where lower is better (the others: higher)
LOWER_IS_BETTER = frozenset(m for m, header in METRICS.items() if header.endswith("↓"))
#: decimals shown per metric
DIGITS = {"psnr": 2, "ssim": 4, "tpsnr": 2, "flip": 4, "relmse": 4}

SEED_SUFFIX = re.compile(r"^(?P<group>.+)_s(?P<seed>\d+)$")


def method_means(rows: Iterable[Mapping], metrics: Sequence[str] = tuple(METRICS)) -> dict[str, dict[str, float]]:
    """``{method: {metric: mean over sequences}}`` from per-sequence rows (first-appearance order)."""
    values: dict[str, dict[str, list[float]]] = {}
    for row in rows:
        per = values.setdefault(str(row["method"]), {m: [] for m in metrics})
        for m in metrics:
            if row.get(m) not in (None, ""):
                per[m].append(float(row[m]))
    return {method: {m: statistics.fmean(v) for m, v in per.items() if v} for method, per in values.items()}


def split_seed(method: str) -> tuple[str, int | None]:
    """``"student_s2"`` -> ``("student", 2)``; a label without the suffix -> ``(label, None)``."""
    match = SEED_SUFFIX.match(method)
    return (match["group"], int(match["seed"])) if match else (method, None)


def seed_groups(means: Mapping[str, Mapping[str, float]]) -> list[dict]:
    """Rows ``{"method", "seeds", "<metric>": mean, "<metric>_std": std}``, one per seed group.

    means: :func:`method_means`' output. ``seeds`` lists the seeds (empty for a method that
    was not trained with a seed suffix, e.g. OIDN).
    """
    groups: dict[str, list[tuple[int | None, Mapping[str, float]]]] = {}
    for method, values in means.items():
        group, seed = split_seed(method)
        groups.setdefault(group, []).append((seed, values))
    rows = []
    for group, members in groups.items():
        row: dict = {"method": group, "seeds": [s for s, _ in members if s is not None]}
        for metric in {m for _, v in members for m in v}:
            xs = [v[metric] for _, v in members if metric in v]
            row[metric] = statistics.fmean(xs)
            row[f"{metric}_std"] = statistics.stdev(xs) if len(xs) > 1 else 0.0
        rows.append(row)
    return rows


def format_mean_std(row: Mapping, metric: str, digits: int) -> str:
    """``"28.31 ± 0.12"`` for a group of several seeds, ``"28.31"`` for a single run."""
    if metric not in row:
        return ""
    text = f"{row[metric]:.{digits}f}"
    return text + f" ± {row[metric + '_std']:.{digits}f}" if len(row.get("seeds", [])) > 1 else text


def group_timing(group: Mapping, bench: Mapping[str, Mapping]) -> Mapping | None:
    """A seed group's bench row: the method's own (e.g. ``OIDN-fast``), else its first timed
    seed's (``student_s0``; the networks of a group are the same size), else None.

    group: a :func:`seed_groups` row; bench: ``{method label: bench row}``.
    """
    if group["method"] in bench:
        return bench[group["method"]]
    return next((bench[f"{group['method']}_s{s}"] for s in group["seeds"] if f"{group['method']}_s{s}" in bench), None)


def tree_hash(root: str | os.PathLike) -> str:
    """SHA-256 over the relative paths and bytes of every file under ``root`` (sorted): the
    content hash of a split, so a report names exactly the frames it was measured on."""
    digest = hashlib.sha256()
    root = Path(root)
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(root)).encode() + b"\0")
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    return digest.hexdigest()


def git_commit() -> str:
    """The checkout's short commit (``-dirty`` with uncommitted changes to tracked files), or
    ``unknown`` outside a git checkout: what a report names as the code that wrote it."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               check=False, text=True).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
