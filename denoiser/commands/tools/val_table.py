"""Training candidates on validation splits: ``python -m denoiser.commands.tools.val_table`` -> ``out``.

Usage::

    python -m denoiser.commands.tools.val_table out=reports/fast/val_table.md reference=base candidates=[base,clamp,dc] \
        "evals={blender: {title: 'Blender Cycles val (fast_101-103)', csv: reports/fast/blender_val/metrics.csv}, \
                mitsuba: {title: 'Mitsuba val (data/demo_fast/val)', csv: reports/fast/mitsuba_val/metrics.csv}}"

A Hydra app over ``conf/val_table.yaml`` (issue 33's val study, retired from the Makefile, ran it
over issue 33's candidates; the command above is that study's first table). It reads every ``metrics.csv`` named under ``evals``
(``denoiser-eval ... split=val``; every candidate's runs labelled ``<group>_s<seed>``, baselines
such as ``noisy input`` and ``OIDN-fast`` without the suffix) and writes, per evaluation:

(``csv`` may also be a list: evaluation runs of the same split, read as one. A method in more than
one of them is taken from the first, and must have the same values in the others: a baseline's
rows that differ mean the runs did not see the same frames, one error line naming both files.
``prefix``, a list as long as ``csv``, renames each file's methods other than the baselines
(``plain_rows`` and ``baseline``): ``prefix: [prev_, '']`` pairs make demo's students of an earlier
run, ``prev_student_distilled_s<k>``, with this run's on the same split.)

* a table: the ``plain_rows`` (methods without seeds, e.g. the noisy input and OIDN), then every candidate (``reference`` first) with the mean over
  sequences of ``metric`` and of each ``also`` column (mean ± std over seeds,
  :mod:`denoiser.report.seed_groups`), and two paired differences in ``metric``: the candidate minus
  ``reference`` and minus ``baseline``, per sequence with the seeds averaged first, their 95% bootstrap
  interval over sequences and the verdict ahead/tied/behind
  (:func:`denoiser.report.seed_groups.paired_difference`, :mod:`denoiser.report.stats`); the
  ``labels`` of the groups shown as a legend under it;
* a per-sequence table of ``metric``, seeds averaged, one column per method shown.

The header names the run id, commit, seeds, the command line and the inputs (with their
SHA-256), under ``title`` (another for a test split: its candidates are then
fixed, and the split is looked at once). Runs of seeds outside ``seeds`` are left out (and named). Missing input (a file, a
baseline, a candidate, one of its seeds) is one error line and exit code 2.
"""

from __future__ import annotations

import datetime
import hashlib
from pathlib import Path

from omegaconf import DictConfig, ListConfig

from denoiser.atomic import atomic_write_text
from denoiser.commands.app import hydra_runtime
from denoiser.errors import ConfigError, UserError
from denoiser.metrics import COLUMNS
from denoiser.report.provenance import git_commit
from denoiser.report.seed_groups import (
    format_interval,
    format_mean_std,
    group_sequences,
    method_means,
    paired_difference,
    seed_groups,
    sequence_values,
    split_seed,
)
from denoiser.report.stats import CONFIDENCE, RESAMPLES, SEED
from denoiser.tables import markdown_table, read_csv


def check_config(cfg: DictConfig) -> tuple[str, list[str], dict[str, dict[str, str]]]:
    """``(metric, also, evals {key: {title, csv: [paths]}})`` of the config; ConfigError on an
    unknown column or an evaluation without a csv."""
    metric, also = str(cfg.metric), [str(m) for m in (cfg.get("also") or [])]
    unknown = [m for m in [metric, *also] if m not in COLUMNS]
    if unknown:
        raise ConfigError(f"metric/also: unknown {unknown} (one of {', '.join(COLUMNS)})")
    evals = {}
    for key, spec in (cfg.get("evals") or {}).items():
        if not spec or not spec.get("csv"):
            raise ConfigError(f"evals.{key}: needs csv (denoiser-eval's metrics.csv) and title")
        csvs = [str(c) for c in spec.csv] if isinstance(spec.csv, (list, ListConfig)) else [str(spec.csv)]
        prefixes = [str(p) for p in spec.get("prefix") or [""] * len(csvs)]
        if len(prefixes) != len(csvs):
            raise ConfigError(f"evals.{key}.prefix: {len(prefixes)} prefixes for {len(csvs)} csv files")
        evals[str(key)] = {"title": str(spec.get("title") or key), "csv": csvs, "prefix": prefixes}
    if not evals:
        raise ConfigError("evals: no evaluation configured ({key: {title, csv}})")
    if not cfg.get("reference"):
        raise ConfigError("reference: the seed group every candidate is compared against")
    return metric, [m for m in dict.fromkeys(also) if m != metric], evals


def keep_seeds(rows: list[dict], seeds: list[int] | None) -> tuple[list[dict], list[str]]:
    """``(rows, methods left out)``: the rows of runs whose seed is not in ``seeds`` removed
    (methods without a seed suffix are kept); every row with ``seeds`` None."""
    if seeds is None:
        return rows, []
    kept, dropped = [], {}
    for row in rows:
        seed = split_seed(str(row["method"]))[1]
        if seed is None or seed in seeds:
            kept.append(row)
        else:
            dropped[str(row["method"])] = True
    return kept, list(dropped)


def merged_rows(paths: list[Path], columns: list[str], prefixes: list[str] | None = None,
                keep: frozenset[str] = frozenset()) -> list[dict]:
    """The rows of every metrics.csv of ``paths`` (runs of one split) as one: each file's methods
    but those in ``keep`` renamed with its entry of ``prefixes``; a method found in an earlier file
    is skipped in a later one, after a check that its ``columns`` agree on every sequence
    (UserError naming both files where not)."""
    rows, first = [], {}
    for path, prefix in zip(paths, prefixes or [""] * len(paths)):
        if not path.exists():
            raise UserError(f"{path}: not found (denoiser-eval ... split=val writes it)")
        own = [r if str(r["method"]) in keep else {**r, "method": prefix + str(r["method"])} for r in read_csv(path)]
        seen = {str(r["method"]) for r in own} & set(first)
        for name in sorted(seen):
            before, now = ({(r["sequence"], c): r.get(c) for r in rs if str(r["method"]) == name for c in columns}
                           for rs in (rows, own))
            differ = [k for k in before.keys() | now.keys() if not _same(before.get(k), now.get(k))]
            if differ:
                seq, column = min(differ)
                raise UserError(f"{path}: method '{name}' differs from {first[name]} on {seq} ({column}; "
                                f"{len(differ)} value(s)): not evaluations of the same split")
        for r in own:
            first.setdefault(str(r["method"]), path)
        rows += [r for r in own if str(r["method"]) not in seen]
    return rows


def joined(paths: list[Path]) -> Path:
    """The one path, or ``a + b`` for runs read as one (how errors and the header name them)."""
    return paths[0] if len(paths) == 1 else Path(" + ".join(map(str, paths)))


def _same(a, b) -> bool:
    try:
        return abs(float(a) - float(b)) <= 1e-6 * max(1.0, abs(float(a)))
    except (TypeError, ValueError):
        return a == b


def evaluation(paths: list[Path], cfg: DictConfig, columns: list[str], seeds: list[int] | None,
               prefixes: list[str] | None = None) -> tuple[list[str], list[str], dict[str, dict], dict, list[str]]:
    """``(baselines, candidates, {name: seed group row}, per-sequence values per group, methods left
    out)`` of one or more metrics.csv (:func:`merged_rows`); UserError naming the file when a
    baseline, a candidate or one of its seeds is missing."""
    path = joined(paths)  # named in errors
    keep = frozenset([*map(str, cfg.get("plain_rows") or []), *([str(cfg.baseline)] if cfg.get("baseline") else [])])
    rows, dropped = keep_seeds(merged_rows(paths, columns, prefixes, keep), seeds)
    groups = {g["method"]: g for g in seed_groups(method_means(rows, columns))}
    base = str(cfg.reference)
    if cfg.get("candidates") is None:
        candidates = [g for g in groups if groups[g]["seeds"]]
    else:
        candidates = [str(c) for c in cfg.candidates]
    candidates = list(dict.fromkeys(candidates if base in candidates else [base, *candidates]))
    baselines = [str(b) for b in (cfg.get("plain_rows") or [])]
    needed = [*baselines, *([str(cfg.baseline)] if cfg.get("baseline") else [])]
    for name in needed:
        if name not in groups:
            raise UserError(f"{path}: no method '{name}' (plain_rows/baseline; methods evaluated: "
                            f"{', '.join(groups)})")
    have = ", ".join(g for g in groups if groups[g]["seeds"]) or "none"
    for name in candidates:
        if name not in groups or not groups[name]["seeds"]:
            raise UserError(f"{path}: no runs of candidate '{name}' (methods {name}_s<seed>; seed groups "
                            f"evaluated: {have})")
        missing = [s for s in (seeds or []) if s not in groups[name]["seeds"]]
        if missing:
            raise UserError(f"{path}: candidate '{name}' lacks seed(s) {missing} of seeds={seeds} "
                            f"(evaluated: {sorted(groups[name]['seeds'])})")
    return baselines, candidates, groups, group_sequences(sequence_values(rows, columns)), dropped


def difference_cell(per_sequence: dict, name: str, other: str, column: str, n: int) -> str:
    """``"+0.32 [+0.13, +0.60] ahead"``: the paired difference name minus other over the sequences
    both have, its interval and verdict (``(k sequences)`` added when they share fewer than ``n``);
    empty for the method itself or without a common sequence."""
    iv = None if name == other else paired_difference(per_sequence, name, other, column)
    if iv is None:
        return ""
    text = f"{format_interval(iv, column)} {iv.verdict(COLUMNS[column].lower_is_better)}"
    return text + (f" ({iv.n} sequences)" if iv.n != n else "")


def candidate_table(cfg: DictConfig, baselines: list[str], candidates: list[str], groups: dict,
                    per_sequence: dict, metric: str, also: list[str], n: int) -> str:
    """Method, seeds (runs), every mean column, then the paired differences in ``metric`` of every
    candidate against ``reference`` and ``baseline``."""
    base, baseline = str(cfg.reference), (str(cfg.baseline) if cfg.get("baseline") else None)
    rows = []
    for name in [*baselines, *candidates]:
        g = groups[name]
        row = {"method": name, "seeds": len(g["seeds"]) or 1,
               **{m: format_mean_std(g, m, COLUMNS[m].digits) for m in [metric, *also]}}
        if name in candidates:
            row["d_base"] = difference_cell(per_sequence, name, base, metric, n)
            if baseline is not None:
                row["d_baseline"] = difference_cell(per_sequence, name, baseline, metric, n)
        rows.append(row)
    interval = f"{COLUMNS[metric].label} [{CONFIDENCE:.0%}]"
    headers = {**{m: COLUMNS[m].header for m in [metric, *also]},
               "d_base": f"vs {base}, {interval}", "d_baseline": f"vs {baseline}, {interval}"}
    columns = ["method", "seeds", metric, *also, "d_base", *(["d_baseline"] if baseline is not None else [])]
    return markdown_table(rows, columns, headers=headers)


def sequence_table(names: list[str], per_sequence: dict, metric: str) -> str:
    """One row per sequence (first-appearance order over ``names``), one column per method: its
    ``metric`` on that sequence, seeds averaged (:func:`denoiser.report.seed_groups.group_sequences`)."""
    values = {name: per_sequence.get(name, {}).get(metric, {}) for name in names}
    sequences = list(dict.fromkeys(seq for v in values.values() for seq in v))
    rows = [{"sequence": seq, **{name: values[name].get(seq) for name in names}} for seq in sequences]
    formats = dict.fromkeys(names, f".{COLUMNS[metric].digits}f")
    return markdown_table(rows, ["sequence", *names], formats=formats)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(cfg: DictConfig) -> Path:
    """Write ``out``; returns its path."""
    metric, also, evals = check_config(cfg)
    seeds = None if cfg.get("seeds") is None else [int(s) for s in cfg.seeds]
    columns = [metric, *also]
    labels = {str(k): str(v) for k, v in (cfg.get("labels") or {}).items()}
    sections, dropped = [], {}
    for key, spec in evals.items():
        paths = [Path(c) for c in spec["csv"]]
        path = joined(paths)
        baselines, candidates, groups, per_sequence, left_out = evaluation(paths, cfg, columns, seeds, spec["prefix"])
        dropped[path] = left_out
        n = len(per_sequence[str(cfg.reference)].get(metric, {}))
        legend = [f"- `{name}`: {labels[name]}" for name in candidates if name in labels]
        sections.append((key, spec, paths, [
            f"### {spec['title']}: {n} sequences", "",
            "From " + " and ".join(f"`{p}`" for p in paths) + ".", "",
            candidate_table(cfg, baselines, candidates, groups, per_sequence, metric, also, n).rstrip(), "",
            *([*legend, ""] if legend else []),
        ], [
            f"#### {spec['title']}: per sequence, {COLUMNS[metric].label} (seeds averaged)", "",
            sequence_table([*baselines, *candidates], per_sequence, metric).rstrip(), "",
        ]))
    overrides = hydra_runtime()[0]
    command = " ".join(["python -m denoiser.commands.tools.val_table", *overrides])
    lines = [
        f"# {cfg.title}",
        "",
        f"- run id: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')}",
        f"- commit: {git_commit()}",
        f"- seeds (every candidate): {seeds if seeds is not None else 'all evaluated'}",
        f"- command: `{command}`",
        *(f"- {spec['title']}: `{p}`, SHA-256 {sha256(p)}" for _, spec, paths, _, _ in sections for p in paths),
        *(f"- left out of `{p}` (seeds not in {seeds}): {', '.join(d)}" for p, d in dropped.items() if d),
        "",
        (f"Means: over the sequences of each evaluation; mean ± std over seeds for a candidate (column "
         f"seeds: its runs). Intervals ({COLUMNS[metric].label}): per sequence, the candidate's value (mean "
         f"over its seeds) minus {cfg.reference}'s"
         + (f" or {cfg.baseline}'s" if cfg.get("baseline") else "")
         + f"; the mean over sequences and its {CONFIDENCE:.0%} percentile bootstrap interval ({RESAMPLES} "
         f"resamples, seed {SEED}; denoiser/report/stats.py), and the verdict from the interval: ahead when "
         "it lies wholly on the candidate's better side of 0, behind when wholly on the other side, tied "
         "when it holds 0."),
        "",
    ]
    for _, _, _, table, _ in sections:
        lines += table
    for _, _, _, _, per_seq in sections:
        lines += per_seq
    out = Path(cfg.out)
    atomic_write_text(out, "\n".join(lines))
    print(f"wrote {out}")
    return out


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "val_table")()


if __name__ == "__main__":
    main()
