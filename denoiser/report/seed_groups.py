"""Seed groups of an evaluation: per-method means, mean ± std over training seeds, paired claims.

``denoiser-eval`` writes one row per method and sequence (``metrics.csv``: ``method, scene,
sequence, frames, psnr, psnr_f2, ssim, tpsnr, flip, relmse, smape, ...``) and one
``sequence=mean`` row per method. A method trained with several seeds appears once per seed,
labelled ``<group>_s<seed>`` (e.g. ``student_distilled_s0``). :func:`sequence_values` keeps the
per-sequence rows; :func:`method_means` reduces them to one value per method and column (the
mean over sequences, as the evaluation's own "Overall" table); :func:`seed_groups` then gathers
``<group>_s<k>`` methods into one row with the mean and the sample standard deviation over
seeds (std 0 for a single run), in first-appearance order. :func:`merge_identical` shows
methods with the same value on every sequence and column once.

Claims (:func:`claim_rows`): per sequence, a group's value averaged over its seeds
(:func:`group_sequences`) minus the baseline's on the same sequence, and the paired bootstrap
interval of the mean difference (:func:`denoiser.report.stats.paired_interval`); the verdict (ahead,
tied, behind) comes from the interval. Column names, headers, decimals and directions:
:data:`denoiser.metrics.COLUMNS`. :func:`run_row`: a training run directory as a row of a summary's
runs table (its seed from the ``<group>_s<k>`` name). What a summary names as its code and data
(the commit, the split's hash) is :mod:`denoiser.report.provenance`.
"""

from __future__ import annotations

import math
import os
import re
import statistics
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from denoiser.errors import ConfigError
from denoiser.metrics import COLUMNS
from denoiser.report.stats import CONFIDENCE, RESAMPLES, SEED, PairedInterval, paired_interval
from denoiser.tables import markdown_table

#: columns summarised, in table order (header, decimals, direction: denoiser.metrics.COLUMNS)
SUMMARY_COLUMNS = ("psnr", "psnr_all", "psnr_f2", "ssim", "tpsnr", "flip", "relmse")
#: columns read per sequence for the claims: the summarised ones and the flicker without a reference
#: (``warp``, lower is better; an evaluation from before it has none: its claims say "not evaluated")
CLAIM_COLUMNS = (*SUMMARY_COLUMNS, "warp")

SEED_SUFFIX = re.compile(r"^(?P<group>.+)_s(?P<seed>\d+)$")

#: ``{method: {column: {sequence: value}}}``
SequenceValues = dict[str, dict[str, dict[str, float]]]


def _number(value) -> float | None:
    """A CSV cell as a float; None for an empty or NaN cell."""
    if value in (None, ""):
        return None
    value = float(value)
    return None if math.isnan(value) else value


def sequence_values(rows: Iterable[Mapping], columns: Sequence[str] = CLAIM_COLUMNS) -> SequenceValues:
    """``{method: {column: {sequence: value}}}`` from ``metrics.csv`` rows (first-appearance
    order; the ``sequence=mean`` rows and empty cells skipped)."""
    values: SequenceValues = {}
    for row in rows:
        per = values.setdefault(str(row["method"]), {c: {} for c in columns})
        if str(row["sequence"]) == "mean":
            continue
        for c in columns:
            if (value := _number(row.get(c))) is not None:
                per[c][str(row["sequence"])] = value
    return values


def method_means(rows: Iterable[Mapping], metrics: Sequence[str] = SUMMARY_COLUMNS) -> dict[str, dict[str, float]]:
    """``{method: {column: mean over sequences}}`` from per-sequence rows (first-appearance order)."""
    return {method: {c: statistics.fmean(v.values()) for c, v in per.items() if v}
            for method, per in sequence_values(rows, metrics).items()}


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


def group_sequences(values: SequenceValues) -> SequenceValues:
    """``{group: {column: {sequence: mean over the group's seeds}}}`` from :func:`sequence_values`'
    output; a sequence counts only where every seed of the group has it."""
    members: dict[str, list[dict[str, dict[str, float]]]] = {}
    for method, per in values.items():
        members.setdefault(split_seed(method)[0], []).append(per)
    out: SequenceValues = {}
    for group, runs in members.items():
        out[group] = {}
        for c in runs[0]:
            common = [seq for seq in runs[0][c] if all(seq in run[c] for run in runs)]
            out[group][c] = {seq: statistics.fmean(run[c][seq] for run in runs) for seq in common}
    return out


def merge_identical(groups: Sequence[Mapping], per_sequence: SequenceValues) -> list[dict]:
    """Seed groups with the same value on every sequence and column shown once: the first such
    row, its method ``"A = B"`` and ``members`` ``[A, B]`` (e.g. two OIDN qualities that run the
    same weights); other rows unchanged. groups: :func:`seed_groups`' rows; per_sequence:
    :func:`group_sequences`' output."""
    out: list[dict] = []
    firsts: dict[str, dict] = {}  # a group's per-sequence values, as a key -> its output row
    for g in groups:
        values = per_sequence.get(g["method"], {})
        key = repr(sorted((c, sorted(v.items())) for c, v in values.items() if v))
        if any(values.values()) and key in firsts:
            first = firsts[key]
            first["members"].append(g["method"])
            first["method"] = " = ".join(first["members"])
            continue
        row = {**g, "members": [g["method"]]}
        firsts.setdefault(key, row)
        out.append(row)
    return out


def check_claims(claims: Iterable[Mapping]) -> list[dict]:
    """Claims of a summary config, checked: ``[{"network", "baseline", "metrics": [column, ...]}]``."""
    out = []
    for claim in claims:
        metrics = [str(m) for m in (claim.get("metrics") or ["psnr"])] if isinstance(claim, Mapping) else []
        if not isinstance(claim, Mapping) or not claim.get("network") or not claim.get("baseline"):
            raise ConfigError(f"claims: every claim needs a network and a baseline, got {claim!r}")
        unknown = [m for m in metrics if m not in COLUMNS]
        if unknown:
            raise ConfigError(f"claims: unknown metric(s) {unknown} (one of {', '.join(COLUMNS)})")
        out.append({"network": str(claim["network"]), "baseline": str(claim["baseline"]), "metrics": metrics})
    return out


def paired_difference(per_sequence: SequenceValues, network: str, baseline: str, column: str,
                      sequences: Iterable[str] | None = None) -> PairedInterval | None:
    """The interval of ``network - baseline`` in ``column`` over the sequences both have (only
    those of ``sequences`` when given); None when they share none. per_sequence:
    :func:`group_sequences`' output (a group's value is the mean over its seeds)."""
    a = per_sequence.get(network, {}).get(column, {})
    b = per_sequence.get(baseline, {}).get(column, {})
    keep = None if sequences is None else set(sequences)
    common = [seq for seq in a if seq in b and (keep is None or seq in keep)]
    return paired_interval([a[q] for q in common], [b[q] for q in common]) if common else None


def _signed(value: float, digits: int) -> str:
    """``"+0.18"``; a value that rounds to zero is ``"+0.00"`` (never ``"-0.00"``)."""
    text = f"{value:+.{digits}f}"
    return "+" + text[1:] if float(text) == 0 else text


def format_interval(iv: PairedInterval, column: str) -> str:
    """``"+0.18 [+0.05, +0.31]"``: the mean difference and its interval, at the column's decimals."""
    d = COLUMNS[column].digits
    return f"{_signed(iv.mean, d)} [{_signed(iv.lo, d)}, {_signed(iv.hi, d)}]"


VERDICT_PHRASE = {"ahead": "is ahead of", "tied": "is tied with", "behind": "is behind"}


def claim_lines(claims: Sequence[Mapping], per_sequence: SequenceValues) -> list[str]:
    """Markdown lines: the table of the claims' paired differences (mean, interval, half-width,
    sequences, verdict), a sentence per claim and metric, and the claims that cannot be made
    (a method or metric not evaluated). claims: :func:`check_claims`' output."""
    rows, sentences, missing = [], [], []
    for claim in claims:
        net, base = claim["network"], claim["baseline"]
        for column in claim["metrics"]:
            spec = COLUMNS[column]
            iv = paired_difference(per_sequence, net, base, column)
            if iv is None:
                missing.append(f"{net} vs {base} ({spec.label})")
                continue
            verdict = iv.verdict(spec.lower_is_better)
            rows.append({"network": net, "baseline": base, "metric": spec.header,
                         "difference": format_interval(iv, column), "half": f"{iv.half_width:.{spec.digits}f}",
                         "n": iv.n, "verdict": verdict})
            sentences.append(f"- {net} {VERDICT_PHRASE[verdict]} {base} on {spec.label}: "
                             f"{format_interval(iv, column)} (± {iv.half_width:.{spec.digits}f}, {iv.n} sequences).")
    if not rows:
        return [f"Claims not made (a method or metric not evaluated): {', '.join(missing)}."] if missing else []
    lines = [(f"Paired differences, network minus baseline: per test sequence, the network's value (mean over "
             f"its seeds) minus the baseline's; the mean over sequences and its {CONFIDENCE:.0%} percentile "
             f"bootstrap interval ({RESAMPLES} resamples, seed {SEED}; denoiser/report/stats.py). Verdict from the "
             "interval, not the means: ahead when it lies wholly on the network's better side of 0 (above 0 for "
             "↑ metrics, below 0 for ↓ ones), behind when wholly on the other side, tied when it holds 0."), ""]
    lines += [markdown_table(rows, ["network", "baseline", "metric", "difference", "half", "n", "verdict"],
                             headers={"difference": f"mean [{CONFIDENCE:.0%} interval]", "half": "±",
                                      "n": "sequences"}).rstrip(), "", *sentences]
    if missing:
        lines.append(f"- not evaluated: {', '.join(missing)}")
    return lines


def family_lines(claims: Sequence[Mapping], per_sequence: SequenceValues, families: Mapping[str, str],
                 column: str) -> list[str]:
    """Markdown lines of the per-family table: one row per family (``families``: ``{sequence:
    family}``, e.g. the ``scene`` column of metrics.csv), one column per claim with the paired
    difference in ``column`` over that family's sequences, its interval and verdict (a family of one
    sequence: the difference alone, since one value has no interval)."""
    spec = COLUMNS[column]
    pairs = [(c["network"], c["baseline"]) for c in claims]
    by_family: dict[str, list[str]] = {}
    for seq, family in families.items():
        by_family.setdefault(family, []).append(seq)
    rows = []
    for family, seqs in by_family.items():
        row: dict = {"family": family, "n": len(seqs)}
        for net, base in pairs:
            iv = paired_difference(per_sequence, net, base, column, seqs)
            if iv is not None and iv.n < 2:  # one sequence has no spread to resample: its difference alone
                row[f"{net} - {base}"] = f"{_signed(iv.mean, spec.digits)} (one sequence)"
            elif iv is not None:
                row[f"{net} - {base}"] = f"{format_interval(iv, column)} {iv.verdict(spec.lower_is_better)}"
        rows.append(row)
    return [(f"Per family: {spec.header}, the same paired differences over each family's sequences "
             f"(mean [{CONFIDENCE:.0%} interval] verdict; a family of one sequence: its difference, no "
             "interval and no verdict)."), "",
            markdown_table(rows, ["family", "n", *(f"{n} - {b}" for n, b in pairs)],
                           headers={"n": "sequences"}).rstrip()]


def format_mean_std(row: Mapping, metric: str, digits: int) -> str:
    """``"28.31 ± 0.12"`` for a group of several seeds, ``"28.31"`` for a single run."""
    if metric not in row:
        return ""
    text = f"{row[metric]:.{digits}f}"
    return text + f" ± {row[metric + '_std']:.{digits}f}" if len(row.get("seeds", [])) > 1 else text


def group_timing(group: Mapping, bench: Mapping[str, Mapping]) -> Mapping | None:
    """A seed group's bench row: the method's own (e.g. ``OIDN-fast``), else its first timed
    seed's (``student_s0``; the networks of a group are the same size), else None; for a merged
    row, its first member's.

    group: a :func:`seed_groups` row; bench: ``{method label: bench row}``.
    """
    name = (group.get("members") or [group["method"]])[0]  # a merged row (merge_identical): its first
    if name in bench:
        return bench[name]
    return next((bench[f"{name}_s{s}"] for s in group["seeds"] if f"{name}_s{s}" in bench), None)


def run_row(run: str | os.PathLike) -> dict:
    """A training run directory as a table row: ``run`` (its name), ``seed`` (of a ``<group>_s<k>``
    name), ``steps`` (``checkpoints/last.ckpt``), ``val_psnr`` (the best validation PSNR that
    ``checkpoints/best.ckpt`` records) and ``collapsed`` (``yes`` where the CollapseDetector left
    ``COLLAPSED``); a key is absent where its file is."""
    from denoiser.checkpoint import read_checkpoint

    run = Path(run)
    row: dict = {"run": run.name, "seed": split_seed(run.name)[1]}
    last, best = run / "checkpoints" / "last.ckpt", run / "checkpoints" / "best.ckpt"
    if last.exists():
        row["steps"] = int(read_checkpoint(last)["global_step"])
    if best.exists():
        for key, state in read_checkpoint(best)["callbacks"].items():
            if "val/psnr" in key and isinstance(state, dict) and state.get("best_model_score") is not None:
                row["val_psnr"] = float(state["best_model_score"])
    row["collapsed"] = "yes" if (run / "COLLAPSED").exists() else "no"
    return row
