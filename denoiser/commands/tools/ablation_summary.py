"""The ablations' summary: ``python -m denoiser.commands.tools.ablation_summary`` -> ``reports/ablations/summary.md``.

Usage::

    python -m denoiser.commands.tools.ablation_summary report=reports/ablations seeds=[0,1,2]

A Hydra app over ``conf/ablation_summary.yaml``, run by ``conf/pipeline/ablations.yaml`` (``make
ablations``) at its end. It reads

* ``<report>/eval/metrics.csv`` (``denoiser-eval`` on the demo's test split; every variant's runs
  labelled ``<variant>_s<seed>``, a variant being an ablation name, ``none`` the full recipe):
  the means ± std over seeds (:mod:`denoiser.report.seed_groups`), and per variant and metric the paired
  difference variant minus ``reference`` per test sequence (seeds averaged per sequence first),
  its 95% bootstrap interval over sequences and the verdict ahead/tied/behind
  (:func:`denoiser.report.seed_groups.paired_difference`, :mod:`denoiser.report.stats`);
* ``<report>/bench/bench.csv`` (``denoiser-bench`` at 1920x1080): ms per frame per variant and
  backend, and what the pyramid costs against each figure variant; with ``bench.json`` beside
  it, the cost paired per interleaved round, its median and distribution-free interval
  (:func:`denoiser.measure.median_interval`);
* each run directory (``run_dirs``, else ``<report>/runs/<variant>_s<seed>``): steps, best val
  PSNR, collapse marker and the teacher it was taught by;
* OIDN (``oidn``, ``OIDN-fast``) when metrics.csv has it (``make ablations`` on your own data,
  ``oidn=true``): a row of each table, a column of every variant's paired difference against it on
  ``decide_metric``, and a sentence on the full recipe against it;

and writes ``summary.md``: the run id, the commit the evaluation ran at (``<report>/eval/evaluation.json``;
the summary's own, said so, without one), seeds, teacher and test-split hash, then between
``<!-- ablations:begin -->`` and ``<!-- ablations:end -->`` (``make readme`` copies it
into docs/results.md) the test ledger's line (how many times the split has been evaluated, in
``ledger``, and which look this evaluation is: :func:`denoiser.report.ledger.looks_line`), the Fig. A.1 tables with one sentence per claim of the paper (holds or does not
hold, with the interval) and the ablations table with one sentence per ablation (the paper's
direction holds or not here); below it the crop figure (``crops_a1.png``: ``denoiser-eval``'s
crop image of one test sequence, the same frame of the figure's variants) and the runs table.
Missing input (a file, a variant, a seed) is one error line and exit code 2.
"""

from __future__ import annotations

import datetime
import json
import os
import shutil
import statistics
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from denoiser.atomic import atomic_write_text
from denoiser.errors import ConfigError, UserError
from denoiser.measure import median_interval
from denoiser.metrics import COLUMNS
from denoiser.report import ledger
from denoiser.report.provenance import commit_line, tree_hash
from denoiser.report.seed_groups import (
    format_interval,
    format_mean_std,
    group_sequences,
    method_means,
    paired_difference,
    run_row,
    seed_groups,
    sequence_values,
)
from denoiser.report.stats import CONFIDENCE, RESAMPLES, SEED
from denoiser.tables import markdown_table, read_csv

#: the README copies the lines between these markers (scripts/readme_results.py --marker ablations)
BEGIN, END = "<!-- ablations:begin -->", "<!-- ablations:end -->"
#: what each expectation of the paper accepts as the variant's verdict against the reference
EXPECTED = {"behind": ("behind",), "not_ahead": ("tied", "behind")}
#: the crop figure, beside summary.md
CROP_FIGURE = "crops_a1.png"


def check_config(cfg: DictConfig) -> tuple[list[str], dict[str, str], dict[str, dict]]:
    """``(metrics, figure variants {name: label}, ablations {name: {label, paper, direction}})``
    of the config, restricted to ``variants`` when given; ConfigError on an unknown metric or
    expectation."""
    metrics = [str(m) for m in cfg.metrics]
    unknown = [m for m in [*metrics, cfg.decide_metric] if m not in COLUMNS]
    if unknown:
        raise ConfigError(f"metrics/decide_metric: unknown {unknown} (one of {', '.join(COLUMNS)})")
    figure = {str(k): str(v) for k, v in (cfg.figure.variants or {}).items()}
    ablations = {str(k): dict(v) for k, v in (cfg.ablations or {}).items()}
    for name, spec in ablations.items():
        if spec.get("paper") not in EXPECTED:
            raise ConfigError(f"ablations.{name}.paper: {spec.get('paper')!r}, expected one of {', '.join(EXPECTED)}")
    if cfg.get("variants") is not None:
        keep = {str(v) for v in cfg.variants}
        known = {str(cfg.reference), *figure, *ablations}
        if keep - known:
            raise ConfigError(f"variants: unknown {sorted(keep - known)} (configured: {', '.join(sorted(known))})")
        figure = {k: v for k, v in figure.items() if k in keep}
        ablations = {k: v for k, v in ablations.items() if k in keep}
    return metrics, figure, ablations


def evaluated_groups(path: Path, wanted: list[str], seeds: list[int]) -> tuple[dict[str, dict], dict]:
    """``({variant: seed group row}, per-sequence values per group)`` of a metrics.csv; UserError
    naming the file when a wanted variant or one of its seeds is missing."""
    rows = read_csv(path)
    groups = {g["method"]: g for g in seed_groups(method_means(rows))}
    for name in wanted:
        if name not in groups or not groups[name]["seeds"]:
            have = ", ".join(g for g in groups if groups[g]["seeds"]) or "none"
            raise UserError(f"{path}: no runs of variant '{name}' (methods {name}_s<seed>; variants evaluated: {have})")
        missing = [s for s in seeds if s not in groups[name]["seeds"]]
        if missing:
            raise UserError(f"{path}: variant '{name}' lacks seed(s) {missing} of seeds={seeds} "
                            f"(evaluated: {sorted(groups[name]['seeds'])})")
    return groups, group_sequences(sequence_values(rows))


# ----------------------------------------------------------------------------- time


def bench_times(csv_path: Path, size: tuple[int, int]) -> tuple[dict[tuple[str, str], dict], dict[str, str]]:
    """``({(method, backend label): row}, {backend label: why not timed})`` at ``size`` (H, W)
    from a denoiser-bench CSV; rows carry ``times_ms`` (per interleaved round) when
    ``bench.json`` lies beside it."""
    per_round = {}
    json_path = csv_path.with_suffix(".json")
    if json_path.exists():
        for r in json.loads(json_path.read_text()).get("rows", []):
            if r.get("times_ms"):
                per_round[(r["method"], r["backend"], int(r["height"]), int(r["width"]))] = r["times_ms"]
    timed, why = {}, {}
    for row in read_csv(csv_path):
        if (int(row["height"]), int(row["width"])) != size:
            continue
        backend = str(row["backend"])
        if row.get("status") != "ok":
            why.setdefault(backend, str(row.get("status")))
            continue
        row["times_ms"] = per_round.get((row["method"], backend, *size))
        timed[(str(row["method"]), backend)] = row
    return timed, {b: w for b, w in why.items() if not any(k[1] == b for k in timed)}


def bench_label(name: str, labels: set[str]) -> str:
    """The bench.csv label of a configured backend label: itself, or with the graph OpenVINO ran
    (``openvino f32`` -> ``openvino f32 (fused)``)."""
    return next((label for label in sorted(labels) if label == name or label.startswith(f"{name} (")), name)


def variant_time(timed: dict, name: str, seeds: list[int], backend: str) -> dict | None:
    """A variant's bench row on ``backend``: its first timed seed's (a variant's seeds are the same network)."""
    return next((timed[(f"{name}_s{s}", backend)] for s in seeds if (f"{name}_s{s}", backend) in timed), None)


def pyramid_cost(ref: dict, other: dict) -> dict:
    """What the reference (the pyramid) costs over ``other``: ``ms`` (difference of the medians),
    ``pct`` (ratio of the medians - 1), and with per-round times of both, ``lo``/``hi``/``median``
    of the per-round ratio - 1 (:func:`~denoiser.measure.median_interval`) and its ``coverage``."""
    out = {"ms": float(ref["ms_median"]) - float(other["ms_median"]),
           "pct": float(ref["ms_median"]) / float(other["ms_median"]) - 1}
    a, b = ref.get("times_ms"), other.get("times_ms")
    if a and b and len(a) == len(b):
        s = median_interval([x / y for x, y in zip(a, b)])
        out.update(median=s["median"] - 1, lo=s["lo"] - 1, hi=s["hi"] - 1, coverage=s["coverage"], rounds=s["runs"])
    return out


def cost_text(cost: dict) -> str:
    """``"+49 ms (+3.3%, paired +3.1% [+1.0%, +5.2%])"``."""
    text = f"{cost['ms']:+.0f} ms ({cost['pct']:+.1%}"
    if "lo" in cost:
        text += f", paired {cost['median']:+.1%} [{cost['lo']:+.1%}, {cost['hi']:+.1%}]"
    return text + ")"


# ----------------------------------------------------------------------------- claims


def difference_cell(per_sequence: dict, name: str, reference: str, column: str) -> str:
    """``"-0.52 [-0.70, -0.35] behind"``: the paired difference name minus reference, its interval
    and verdict; empty when they share no sequence."""
    iv = paired_difference(per_sequence, name, reference, column)
    return "" if iv is None else f"{format_interval(iv, column)} {iv.verdict(COLUMNS[column].lower_is_better)}"


def verdict_text(per_sequence: dict, name: str, reference: str, column: str, ref_label: str) -> tuple[str, str]:
    """``(verdict, "no_pyramid is behind the pyramid student on PSNR dB: -0.52 [-0.70, -0.35] (± 0.18,
    42 sequences)")``."""
    spec = COLUMNS[column]
    iv = paired_difference(per_sequence, name, reference, column)
    if iv is None:
        raise UserError(f"{name} and {reference}: no common test sequence with {column}")
    verdict = iv.verdict(spec.lower_is_better)
    phrase = {"ahead": "is ahead of", "tied": "is tied with", "behind": "is behind"}[verdict]
    return verdict, (f"{name} {phrase} {ref_label} on {spec.label}: {format_interval(iv, column)} "
                     f"(± {iv.half_width:.{spec.digits}f}, {iv.n} sequences)")


def other_verdicts(per_sequence: dict, name: str, reference: str, metrics: list[str], decided: str) -> str:
    """``"SSIM behind, FLIP behind, tPSNR dB tied"``: the verdicts of the other metrics."""
    out = []
    for m in metrics:
        iv = paired_difference(per_sequence, name, reference, m) if m != decided else None
        if iv is not None:
            out.append(f"{COLUMNS[m].label} {iv.verdict(COLUMNS[m].lower_is_better)}")
    return ", ".join(out)


def collapse_note(runs: list[dict], name: str) -> str:
    bad = [r for r in runs if r["variant"] == name and r.get("collapsed") == "yes"]
    n = sum(r["variant"] == name for r in runs)
    return f" {len(bad)} of its {n} runs collapsed (runs table): their numbers are those of a broken run." if bad else ""


def noise_lines(cfg: DictConfig, figure: dict, per_sequence: dict, metrics: list[str], runs: list[dict]) -> list[str]:
    """One sentence per figure variant on the paper's noise claim: holds when the variant is behind."""
    ref, column = str(cfg.reference), str(cfg.decide_metric)
    lines = []
    for name, label in figure.items():
        verdict, text = verdict_text(per_sequence, name, ref, column, "the pyramid student")
        holds = verdict == "behind"
        others = other_verdicts(per_sequence, name, ref, metrics, column)
        lines.append(f"- The paper: \"{cfg.figure.noise_claim}\" ({name}: {label}): **{'holds' if holds else 'does not hold'}"
                     f"** here: {text}" + (f"; {others}." if others else ".")
                     + ("" if holds else " The crop figure below shows the same frame of both.")
                     + collapse_note(runs, name))
    return lines


def runtime_line(cfg: DictConfig, timed: dict, why: dict, seeds: list[int], backends: list[str]) -> str:
    """The sentence on the paper's runtime claim: on every timed backend, the pyramid's cost over
    ``runtime_variant`` against ``runtime_tolerance`` (with the paired interval when there is one:
    holds when its upper end is within the tolerance, does not hold when its lower end exceeds it,
    undecided otherwise; with medians only, the median decides)."""
    ref, other, tol = str(cfg.reference), str(cfg.figure.runtime_variant), float(cfg.figure.runtime_tolerance)
    h, w = (int(v) for v in cfg.bench_size)
    parts, verdicts = [], []
    for b in backends:
        a, o = variant_time(timed, ref, seeds, b), variant_time(timed, other, seeds, b)
        if a is None or o is None:
            if b in why:
                parts.append(f"{b} not timed ({why[b]})")
            continue
        cost = pyramid_cost(a, o)
        if "lo" in cost:
            verdicts.append("holds" if cost["hi"] <= tol else "does not hold" if cost["lo"] > tol else "undecided")
        else:
            verdicts.append("holds" if cost["pct"] <= tol else "does not hold")
        parts.append(f"{b}: {float(a['ms_median']):.0f} ms against {other}'s {float(o['ms_median']):.0f} ms, "
                     f"{cost_text(cost)}")
    if not verdicts:
        overall = "not measured"
    elif "does not hold" in verdicts:
        overall = "does not hold"
    else:
        overall = "holds" if all(v == "holds" for v in verdicts) else "undecided"
    return (f"- The paper: \"{cfg.figure.runtime_claim}\": **{overall}** here (read as: the pyramid student takes "
            f"at most {tol:.0%} more time per {w}x{h} frame than {other}; the paired interval over rounds decides "
            f"where there is one, else the medians): " + ("; ".join(parts) or "no backend timed both") + ".")


def ablation_lines(cfg: DictConfig, ablations: dict, per_sequence: dict, metrics: list[str], runs: list[dict]) -> list[str]:
    """One sentence per ablation: does the paper's direction hold here?"""
    ref, column = str(cfg.reference), str(cfg.decide_metric)
    lines = []
    for name, spec in ablations.items():
        verdict, text = verdict_text(per_sequence, name, ref, column, f"the full recipe ({ref})")
        holds = verdict in EXPECTED[spec["paper"]]
        others = other_verdicts(per_sequence, name, ref, metrics, column)
        lines.append(f"- {name}, {spec['label']}. The paper's direction: {spec['direction']}. It "
                     f"**{'holds' if holds else 'does not hold'}** here: {text}" + (f"; {others}." if others else ".")
                     + collapse_note(runs, name))
    return lines


# ----------------------------------------------------------------------------- tables


def quality_table(names: list[str], groups: dict, per_sequence: dict, reference: str, metrics: list[str],
                  oidn: str | None = None, decide: str = "psnr") -> str:
    """Variant, seeds, every metric's mean ± std over seeds, then every metric's paired difference
    against the reference with its interval and verdict; with ``oidn`` (a method of the evaluation),
    its row (its difference against the reference) and a column of every variant's ``decide``
    difference against it."""
    rows = []
    for name in names + ([oidn] if oidn else []):
        g = groups[name]
        row = {"variant": name, "seeds": len(g["seeds"]) if name != oidn else "",
               **{m: format_mean_std(g, m, COLUMNS[m].digits) for m in metrics}}
        if name != reference:
            row.update({f"d_{m}": difference_cell(per_sequence, name, reference, m) for m in metrics})
        if oidn and name != oidn:
            row["d_oidn"] = difference_cell(per_sequence, name, oidn, decide)
        rows.append(row)
    headers = {**{m: COLUMNS[m].header for m in metrics},
               **{f"d_{m}": f"Δ {COLUMNS[m].label} vs {reference} [95%]" for m in metrics},
               "d_oidn": f"Δ {COLUMNS[decide].label} vs {oidn} [95%]"}
    columns = ["variant", "seeds", *metrics, *(f"d_{m}" for m in metrics)] + (["d_oidn"] if oidn else [])
    return markdown_table(rows, columns, headers=headers)


def oidn_line(per_sequence: dict, reference: str, oidn: str, column: str) -> str:
    """``"- The full recipe (none) is ahead of OIDN-fast on PSNR dB: +1.20 [+0.90, +1.50] (± 0.30, 8 sequences)."``"""
    return "- " + verdict_text(per_sequence, reference, oidn, column, oidn)[1].replace(
        reference, f"The full recipe ({reference})", 1) + "."


def time_table(names: list[str], timed: dict, seeds: list[int], reference: str, backends: list[str],
               size: tuple[int, int]) -> str:
    """Variant, then per backend timed: ms per frame (median over rounds) and the pyramid's cost
    over the variant."""
    rows = []
    for name in names:
        row = {"variant": name}
        for b in backends:
            mine, ref = variant_time(timed, name, seeds, b), variant_time(timed, reference, seeds, b)
            if mine is not None:
                row[f"ms_{b}"] = f"{float(mine['ms_median']):.0f}"
                if ref is not None and name != reference:
                    row[f"cost_{b}"] = cost_text(pyramid_cost(ref, mine))
        rows.append(row)
    h, w = size
    headers = {**{f"ms_{b}": f"ms/frame {w}x{h} {b}" for b in backends},
               **{f"cost_{b}": f"{reference} minus variant, {b}" for b in backends}}
    return markdown_table(rows, ["variant", *(c for b in backends for c in (f"ms_{b}", f"cost_{b}"))], headers=headers)


def teacher_of(run: Path) -> str | None:
    """The ``model.teacher_ckpt=`` a run was trained with (``.hydra/overrides.yaml``), a relative
    path joined to the folder it was trained from (``.hydra/hydra.yaml``'s ``hydra.runtime.cwd``),
    so that one teacher named two ways is one; ``"none"`` without one, None without the overrides."""
    overrides = run / ".hydra" / "overrides.yaml"
    if not overrides.exists():
        return None
    given = [str(o).split("=", 1)[1] for o in OmegaConf.load(overrides) if str(o).startswith("model.teacher_ckpt=")]
    if not given:
        return "none"
    hydra = run / ".hydra" / "hydra.yaml"
    cwd = OmegaConf.select(OmegaConf.load(hydra), "hydra.runtime.cwd") if hydra.exists() else None
    return os.path.normpath(Path(cwd or "") / given[0]) if not Path(given[0]).is_absolute() else given[0]


def run_table_rows(cfg: DictConfig, names: list[str], seeds: list[int]) -> list[dict]:
    """One row per variant and seed: the run directory, steps, best val PSNR, collapse, teacher."""
    report, prefixes = Path(cfg.report), dict(cfg.get("run_dirs") or {})
    rows = []
    for name in names:
        for s in seeds:
            run = Path(f"{prefixes[name]}_s{s}") if name in prefixes else report / "runs" / f"{name}_s{s}"
            row = {"variant": name, "seed": s, "dir": str(run)}
            if run.is_dir():
                row.update({k: v for k, v in run_row(run).items() if k not in ("run", "seed")})
                teacher = teacher_of(run)
                if teacher is not None:
                    row["teacher"] = teacher
            else:
                row["collapsed"] = "not found"
            rows.append(row)
    return rows


def run_notes(rows: list[dict]) -> list[str]:
    """Lines naming what breaks the protocol: runs at different steps, distilled runs taught by different teachers."""
    notes = []
    steps = sorted({r["steps"] for r in rows if "steps" in r})
    if len(steps) > 1:
        notes.append(f"- Not at equal steps: the runs trained {', '.join(map(str, steps))} steps (the runs table of summary.md).")
    teachers = sorted({r["teacher"] for r in rows if r.get("teacher") not in (None, "none")})
    if len(teachers) > 1:
        notes.append(f"- Not the same teacher: {', '.join(f'`{t}`' for t in teachers)}.")
    return notes


# ----------------------------------------------------------------------------- crops


def crop_sequence(cfg: DictConfig, figure: dict, per_sequence: dict) -> str | None:
    """The crop figure's sequence: ``figure.crop_sequence``, else the sequence of the median paired
    difference of the first figure variant against the reference (lower middle for an even count)."""
    if cfg.figure.get("crop_sequence"):
        return str(cfg.figure.crop_sequence)
    if not figure:
        return None
    column, ref = str(cfg.decide_metric), str(cfg.reference)
    a = per_sequence[next(iter(figure))].get(column, {})
    b = per_sequence[ref].get(column, {})
    diffs = sorted((a[q] - b[q], q) for q in a if q in b)
    return diffs[(len(diffs) - 1) // 2][1] if diffs else None


def crop_lines(cfg: DictConfig, report: Path, figure: dict, per_sequence: dict, seeds: list[int]) -> list[str]:
    """Copy denoiser-eval's crop image of the chosen sequence to ``<report>/crops_a1.png`` and
    return the lines showing it (or saying why there is none)."""
    seq = crop_sequence(cfg, figure, per_sequence)
    if seq is None:
        return ["No crop figure: no figure variant evaluated.", ""]
    image = report / "eval" / "images" / f"{seq.replace('/', '_')}.png"
    if not image.exists():
        return [f"No crop figure: `{image}` does not exist (denoiser-eval images.frame=null, or another sequence).", ""]
    shutil.copyfile(image, report / CROP_FIGURE)
    why = ("set by figure.crop_sequence" if cfg.figure.get("crop_sequence") else
           f"the test sequence whose paired {COLUMNS[str(cfg.decide_metric)].label} difference "
           f"{next(iter(figure))} minus {cfg.reference} is the median over the sequences: a typical one, not the best case")
    return [(f"Crops of the same frame (`{seq}`, {why}): the networks of seed {seeds[0]}, as "
            "`denoiser-eval` drew them (`images.methods`; the PSNR under each label is the whole frame's), "
            "beside the noisy input and the reference."), "", f"![Fig. A.1 crops]({CROP_FIGURE})", ""]


# ----------------------------------------------------------------------------- report


def run(cfg: DictConfig) -> Path:
    """Write ``<report>/summary.md``; returns its path."""
    report = Path(cfg.report)
    metrics_csv, bench_csv = report / "eval" / "metrics.csv", report / "bench" / "bench.csv"
    for path, what in ((metrics_csv, "denoiser-eval"), (bench_csv, "denoiser-bench")):
        if not path.exists():
            raise UserError(f"{path}: not found (run {what} first: make ablations)")
    metrics, figure, ablations = check_config(cfg)
    seeds = [int(s) for s in cfg.seeds]
    ref = str(cfg.reference)
    figure_names, ablation_names = [ref, *figure], [ref, *ablations]
    names = [ref, *figure, *ablations]
    groups, per_sequence = evaluated_groups(metrics_csv, names, seeds)
    oidn = str(cfg.oidn) if cfg.get("oidn") and str(cfg.oidn) in groups else None
    decide = str(cfg.decide_metric)
    size = (int(cfg.bench_size[0]), int(cfg.bench_size[1]))
    timed, why = bench_times(bench_csv, size)
    configured = [bench_label(str(b), {k[1] for k in timed} | set(why)) for b in cfg.backends]
    backends = [b for b in configured if any(k[1] == b for k in timed)]
    runs = run_table_rows(cfg, names, seeds)
    test_dir = Path(cfg.data_root) / "test"
    n_seq = statistics.median(len(per_sequence[n].get(str(cfg.decide_metric), {})) for n in names)
    evaluated = ledger.read_provenance(metrics_csv.parent)
    lines = [
        f"# Ablations summary (the paper's Fig. A.1 and distillation ablations on the held-out scenes of `{test_dir}`)",
        "",
        f"- run id: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')}",
        commit_line(evaluated),
        f"- seeds (every variant): {seeds}",
        f"- teacher (every distilled run): `{cfg.teacher}`" if cfg.get("teacher") else "- teacher: not stated",
        f"- test split: `{test_dir}`, SHA-256 of its files {tree_hash(test_dir) if test_dir.is_dir() else 'missing'}",
        "",
        (f"Every variant is the demo student trained by the demo recipe with one change (`ablation=<variant>`; "
        f"`{ref}`: the full recipe, the pyramid student) with seeds {seeds}, for the same steps and by the same "
        f"teacher (the runs table checks both), evaluated on the same {n_seq:.0f} test sequences. Quality: the mean over sequences, mean ± std over seeds. "
        f"Δ: per test sequence, the variant's value (mean over its seeds) minus {ref}'s; the mean over sequences "
        f"and its {CONFIDENCE:.0%} percentile bootstrap interval ({RESAMPLES} resamples, seed {SEED}; "
        "denoiser/report/stats.py), and the verdict from the interval: ahead when it lies wholly on the variant's better "
        "side of 0 (↑: above, ↓: below), behind when wholly on the other side, tied when it holds 0. A claim of "
        f"the paper holds or not by the verdict of {COLUMNS[str(cfg.decide_metric)].label}; the other metrics' "
        "verdicts follow it."),
        "",
        BEGIN,
        ledger.looks_line(evaluated, cfg.get("ledger") or ledger.LEDGER),
        "",
    ]
    if figure:
        h, w = size
        lines += [f"**{cfg.figure.title}** ({', '.join(f'{k}: {v}' for k, v in figure.items())})", "",
                  quality_table(figure_names, groups, per_sequence, ref, metrics, oidn, decide).rstrip(), "",
                  (f"Time per {w}x{h} frame (denoiser-bench, median over interleaved rounds, seed {seeds[0]}'s "
                  f"networks; cost: {ref}'s median minus the variant's, in ms and %, and the ratio paired per round "
                  "with its distribution-free interval where the per-round times are there):"), "",
                  time_table(figure_names, timed, seeds, ref, backends, size).rstrip(), "",
                  *noise_lines(cfg, figure, per_sequence, metrics, runs),
                  runtime_line(cfg, timed, why, seeds, configured) if cfg.figure.runtime_variant in figure
                  else f"- The paper: \"{cfg.figure.runtime_claim}\": not measured ({cfg.figure.runtime_variant} not reported).",
                  ""]
        skipped = [f"{b}: {why[b]}" for b in cfg.backends if str(b) in why]
        if skipped:
            lines += [f"Backends not timed: {'; '.join(skipped)}.", ""]
    if ablations:
        lines += ["**The distillation ablations and the kernel variants** (each against the full recipe)", "",
                  quality_table(ablation_names, groups, per_sequence, ref, metrics, oidn, decide).rstrip(), "",
                  *ablation_lines(cfg, ablations, per_sequence, metrics, runs), ""]
    if oidn:
        lines += [oidn_line(per_sequence, ref, oidn, decide), ""]
    lines += [*run_notes(runs), END, ""]
    if figure:
        lines += [f"## {cfg.figure.title}: crops", "", *crop_lines(cfg, report, figure, per_sequence, seeds)]
    lines += ["## Training runs (steps, best validation PSNR, collapse, teacher)", "",
              markdown_table(runs, ["variant", "seed", "dir", "steps", "val_psnr", "collapsed", "teacher"],
                             formats={"val_psnr": ".2f"}, headers={"val_psnr": "best val PSNR dB"}).rstrip(), ""]
    out = report / "summary.md"
    atomic_write_text(out, "\n".join(lines))
    print(f"wrote {out}")
    return out


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "ablation_summary")()


if __name__ == "__main__":
    main()
