"""An evaluation's summary: ``python -m denoiser.commands.tools.eval_summary`` -> ``<report>/summary.md``.

Usage::

    python -m denoiser.commands.tools.eval_summary report=reports/demo data_root=data/demo seeds=[0,1,2]

One command for three pipelines' summaries, each its own entry config: make demo's
(``conf/demo_summary.yaml``, the default; ``conf/pipeline/demo.yaml`` runs it at its end), make
compare's (``--config-name compare_summary``) and the recipe check's (``--config-name
recipe_check_summary``, ``conf/pipeline/recipe_check.yaml``). It reads

* ``<report>/eval/metrics.csv`` (``denoiser-eval`` on the test split; students labelled
  ``<group>_s<seed>``) and gathers the seeds into mean ± std (:mod:`denoiser.report.seed_groups`), one row
  for methods with identical per-sequence values (``OIDN-balanced = OIDN-high``), and the
  paired claims of ``claims`` (network minus baseline per sequence, a bootstrap interval over
  sequences and a verdict from it), with a per-family table of the same differences;
* ``<report>/bench/bench.csv`` (``denoiser-bench``): ms per 1080p frame per method on its
  fastest backend per precision (fp32, bf16), and the paired speed-up over OIDN-fast with its interval;
* ``<report>/timings.md`` (the pipeline's stage-time table; ``timings.md.tmp`` while it runs): a line
  in the results block with every stage's seconds and their sum;
* every run directory under ``<report>/runs``: steps trained (``last.ckpt``), best val PSNR
  (``best.ckpt``) and its seed;
* each ``<report>/<dir>/metrics.csv`` named under ``extra_evals`` (``{dir: title}``, e.g. the
  demo networks on the Blender Cycles sequences), when it exists: one more table per
  evaluation, with every method's PSNR gain over the noisy input, and its claims;

and writes ``summary.md`` with the run id, the commit the evaluation ran at (``<report>/eval/evaluation.json``,
written by ``denoiser-eval``; the summary's own commit, said so, for an evaluation without one),
seeds, steps, the SHA-256 of the test split's files, and the tables. Each results block opens with
the test ledger's line (:func:`denoiser.report.ledger.looks_line`): how many times its split has been
evaluated (``ledger``: the ledger read) and which look its evaluation is. ``scripts/readme_results.py``
copies a results block (the ledger's line, the table and the claims) into docs/results.md.

``make compare`` (``conf/pipeline/compare.yaml``) runs it over ``conf/compare_summary.yaml``::

    python -m denoiser.commands.tools.eval_summary --config-name compare_summary report=reports/compare seeds=[0,1,2]

which adds the figure tables declared under ``tables`` (the paper's Fig. A.2 and A.3, with
their ranking lines; :mod:`denoiser.report.figure_tables`) above the table of every method.
"""

from __future__ import annotations

import datetime
import re
from pathlib import Path

from omegaconf import DictConfig

from denoiser.atomic import atomic_write_text
from denoiser.errors import ConfigError, UserError
from denoiser.metrics import COLUMNS
from denoiser.report import ledger
from denoiser.report.figure_tables import figure_sections
from denoiser.report.flicker_report import agreement_lines
from denoiser.report.provenance import commit_line, tree_hash
from denoiser.report.seed_groups import (
    SUMMARY_COLUMNS,
    check_claims,
    claim_lines,
    family_lines,
    format_mean_std,
    group_sequences,
    group_timing,
    merge_identical,
    method_means,
    run_row,
    seed_groups,
    sequence_values,
)
from denoiser.tables import markdown_table, read_csv


def markers(name: str) -> tuple[str, str]:
    """The lines around the block the README copies (scripts/readme_results.py --marker <name>):
    ``results`` for make demo's summary, ``compare`` for make compare's (the config's ``marker``)."""
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def run_rows(runs: Path) -> list[dict]:
    """One row per run directory of ``runs`` (by name): seed, steps (last.ckpt), best val PSNR (best.ckpt)."""
    return [run_row(run) for run in sorted(p for p in runs.iterdir() if (p / "checkpoints").is_dir())]


def stage_times(report: Path) -> list[str]:
    """The lines (a blank one, then the line) of the pipeline's stage-time table (``<report>/timings.md``, or ``timings.md.tmp`` while
    the pipeline that runs this summary is still going: the stages before it): every stage's seconds and
    their sum, the wall time of a run that reused nothing. None without a table (the block as before)."""
    from denoiser.pipeline.timings import newest, read_rows

    table = newest(report / "timings.md")
    rows = read_rows(table) if table is not None else {}
    if not rows:
        return []
    total = sum(seconds for seconds, _ in rows.values())
    stages = ", ".join(f"{stage} {seconds}" for stage, (seconds, _) in rows.items())
    machine = bench_machine(report)
    return ["", f"Stage times of the pipeline that made this report: {total} s ({total / 60:.1f} min) in all, "
            f"{stages} (seconds; `{report.as_posix()}/timings.md`)" + (f", on {machine}." if machine else ".")]


def bench_machine(report: Path) -> str | None:
    """The CPU the report's benchmark ran on (``<report>/bench/bench.json``), e.g. ``AMD EPYC
    (AuthenticAMD family 25 model 17), 2 logical cores``; None without a benchmark."""
    import json

    path = report / "bench" / "bench.json"
    if not path.is_file():
        return None
    machine = json.loads(path.read_text()).get("machine") or {}
    if not machine.get("cpu"):
        return None
    cpu_id = f" ({machine['cpu_id']})" if machine.get("cpu_id") else ""
    cores = f", {machine['logical_cores']} logical cores" if machine.get("logical_cores") else ""
    return f"{machine['cpu']}{cpu_id}{cores}"


#: the precisions a summary shows time columns for, in order (f32 first: like with like against OIDN)
PRECISIONS = ("fp32", "bf16")


def bench_rows(path: Path, size: tuple[int, int]) -> dict[str, dict[str, dict]]:
    """``{precision: {method: fastest ok row of that precision at size (H, W)}}`` from a
    ``denoiser-bench`` CSV (precision: its ``dtype`` column, ``fp32`` when empty)."""
    best: dict[str, dict[str, dict]] = {}
    for row in read_csv(path):
        if row.get("status") != "ok" or (int(row["height"]), int(row["width"])) != size:
            continue
        dtype = str(row.get("dtype") or "")
        dtype = "fp32" if dtype in ("", "nan") else dtype
        mine = best.setdefault(dtype, {})
        if row["method"] not in mine or float(row["ms_median"]) < float(mine[row["method"]]["ms_median"]):
            mine[row["method"]] = row
    return best


def speedup_text(timed: dict, ref: dict | None) -> str:
    """``"1.74x (1.60-1.85)"``: the bench's paired speed-up over the reference with its interval
    over rounds (``speedup``/``_lo``/``_hi`` columns), or the ratio of the medians (no interval)
    when the row has none; empty without a reference."""
    if ref is None:
        return ""
    if timed.get("speedup") not in (None, "", "nan") and ref.get("kind") == "baseline":
        mid, lo, hi = (float(timed[k]) for k in ("speedup", "speedup_lo", "speedup_hi"))
        if ref is timed:
            return "1.00x"
        return f"{mid:.2f}x ({lo:.2f}-{hi:.2f})"
    return f"{float(ref['ms_median']) / float(timed['ms_median']):.2f}x"


#: headers of the summarised columns
HEADERS = {c: COLUMNS[c].header for c in SUMMARY_COLUMNS}


def metric_row(group: dict) -> dict:
    """A seed group's table row: method, number of seeds, and every column as mean ± std."""
    return {"method": group["method"], "seeds": len(group["seeds"]) or "",
            **{m: format_mean_std(group, m, COLUMNS[m].digits) for m in SUMMARY_COLUMNS}}


def merged_note(groups: list[dict]) -> list[str]:
    """A paragraph under a table naming its merged rows (:func:`denoiser.report.seed_groups.merge_identical`)."""
    merged = [g["method"] for g in groups if len(g.get("members", [])) > 1]
    note = (f"`{' `, `'.join(merged)}`: the same value on every sequence and metric, one row (OIDN's qualities "
            "run the same weights where its large weights are not installed, as on this CPU).")
    return ["", note] if merged else []


def evaluation(path: Path) -> tuple[list[dict], dict]:
    """A metrics.csv's seed groups (:func:`denoiser.report.seed_groups.seed_groups`) and its per-sequence
    values per group (:func:`denoiser.report.seed_groups.group_sequences`)."""
    rows = read_csv(path)
    return seed_groups(method_means(rows)), group_sequences(sequence_values(rows))


def results_table(groups: list[dict], bench: dict[str, dict[str, dict]], size: tuple[int, int], reference: str) -> str:
    """The results table: metrics (mean ± std over seeds), then per precision (:data:`PRECISIONS`)
    the fastest backend's ms per frame at ``size`` and the paired speed-up over ``reference``
    (which runs fp32 on the CPUs benchmarked: the fp32 column is like with like)."""
    ref = bench.get("fp32", {}).get(reference)
    rows = []
    shown = [p for p in PRECISIONS if p in bench]
    for g in groups:
        row = metric_row(g)
        for p in shown:
            timed = group_timing(g, bench[p])
            if timed:
                row[f"ms_{p}"] = f"{float(timed['ms_median']):.0f} ({timed['backend']})"
                row[f"speedup_{p}"] = speedup_text(timed, ref)
        rows.append(row)
    h, w = size
    columns = ["method", "seeds", *SUMMARY_COLUMNS, *(c for p in shown for c in (f"ms_{p}", f"speedup_{p}"))]
    headers = {**HEADERS, **{f"ms_{p}": f"ms/frame {w}x{h} {p}" for p in shown},
               **{f"speedup_{p}": f"{p} vs {reference} (interval)" for p in shown}}
    return markdown_table(rows, columns, headers=headers)


def gain_table(groups: list[dict], noisy: str = "noisy input") -> str:
    """Seed groups' metrics (mean ± std) and their PSNR gain over ``noisy``'s, one row per group."""
    base = next((g["psnr"] for g in groups if g["method"] == noisy and "psnr" in g), None)
    rows = []
    for g in groups:
        row = metric_row(g)
        if base is not None and "psnr" in g and g["method"] != noisy:
            row["gain"] = f"{g['psnr'] - base:+.2f}"
        rows.append(row)
    return markdown_table(rows, ["method", "seeds", *SUMMARY_COLUMNS, "gain"],
                          headers={**HEADERS, "gain": "PSNR gain dB"})


def extra_sections(report: Path, extra: dict, claims: list[dict], family_metric: str | None = None,
                   book: str | Path = ledger.LEDGER) -> list[str]:
    """Markdown lines of one table (and the claims, and with ``family_metric`` their per-family
    table in that metric) per ``{dir: title}`` whose ``<report>/<dir>/metrics.csv`` exists, between
    ``<!-- <dir>:begin -->`` and ``<!-- <dir>:end -->`` (``make readme`` copies it), the block opening
    with the looks of its split in the test ledger ``book``."""
    lines: list[str] = []
    for name, title in extra.items():
        csv_path = report / str(name) / "metrics.csv"
        if title is not None and csv_path.exists():  # null: an entry of the composed config turned off
            groups, per_sequence = evaluation(csv_path)
            groups = merge_identical(groups, per_sequence)
            by_family = (["", *family_lines(claims, per_sequence, families(csv_path), family_metric), ""]
                         if claims and family_metric else [])
            looks = ledger.looks_line(ledger.read_provenance(csv_path.parent), book)
            lines += [f"## {title}", "", f"From `{csv_path}`; students: mean ± std over seeds.", "",
                      f"<!-- {name}:begin -->", looks, "", gain_table(groups).rstrip(), *merged_note(groups), "",
                      *claim_lines(claims, per_sequence), *by_family, f"<!-- {name}:end -->", ""]
    return lines


def families(path: Path) -> dict[str, str]:
    """``{sequence: family}`` of a metrics.csv's per-sequence rows: the ``scene`` column less a trailing
    ``_<number>``, so that scenes numbered within one kind are one family (the Blender layout's
    ``fast_201``, ``fast_202``, ... are ``fast``; the demo's scenes carry no number)."""
    return {str(r["sequence"]): re.sub(r"_\d+$", "", str(r["scene"])) for r in read_csv(path)
            if str(r["sequence"]) != "mean"}


def run(cfg: DictConfig) -> Path:
    """Write ``<report>/summary.md``; returns its path."""
    report = Path(cfg.report)
    metrics_csv = report / "eval" / "metrics.csv"
    if not metrics_csv.exists():
        raise UserError(f"{metrics_csv}: no evaluation found (run denoiser-eval first)")
    claims = check_claims(cfg.get("claims") or [])
    for key in ("family_metric", "extra_family_metric"):
        if cfg.get(key) is not None and cfg[key] not in COLUMNS:
            raise ConfigError(f"{key}: unknown {cfg[key]!r} (one of {', '.join(COLUMNS)})")
    groups, per_sequence = evaluation(metrics_csv)
    merged = merge_identical(groups, per_sequence)
    size = (int(cfg.bench_size[0]), int(cfg.bench_size[1]))
    bench_csv = report / "bench" / "bench.csv"
    bench = bench_rows(bench_csv, size) if bench_csv.exists() else {}
    runs = run_rows(report / "runs") if (report / "runs").is_dir() else []
    test_dir = Path(cfg.data_root) / "test"
    book = cfg.get("ledger") or ledger.LEDGER
    evaluated = ledger.read_provenance(metrics_csv.parent)
    lines = [
        f"# {cfg.title}",
        "",
        f"- run id: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')}",
        commit_line(evaluated),
        f"- seeds (students): {list(cfg.seeds)}",
        f"- test split: `{test_dir}`, SHA-256 of its files {tree_hash(test_dir) if test_dir.is_dir() else 'missing'}",
        "",
        ("Metrics: the mean over test sequences of each sequence's mean over its frames kept after "
         f"denoiser-eval's warm-up; {COLUMNS['psnr_all'].label}: over every frame; "
         f"{COLUMNS['psnr_f2'].label}: over every frame but each sequence's first "
         "(frames counted from 1, warm-up or not): the quality once the history is in use."),
        "",
    ]
    if cfg.tables:
        lines += [
            ("Every table: the mean over the test sequences; mean ± std over seeds for a method trained with "
             "several seeds (column seeds), one run otherwise; ms per frame from bench/bench.csv: the fastest "
             "backend per precision (fp32 beside bf16; OIDN runs fp32 here, so the fp32 speed-up is like with "
             "like), the median over interleaved rounds, and the speed-up paired per round with its interval "
             "over rounds."),
            "",
            *figure_sections(cfg.tables, groups, bench.get("fp32", {}), size, list(cfg.table_metrics), cfg.rank_metric),
        ]
    lines += [
        "## Test split, every method" if cfg.tables else "## Test split (students: mean ± std over seeds)",
        "",
        markers(cfg.marker)[0],
        ledger.looks_line(evaluated, book),
        "",
        results_table(merged, bench, size, cfg.speed_reference).rstrip(),
        *merged_note(merged),
        "",
        *claim_lines(claims, per_sequence),
        *stage_times(report),
        markers(cfg.marker)[1],
        "",
        *(family_lines(claims, per_sequence, families(metrics_csv), cfg.family_metric) + [""] if claims else []),
        *(agreement_lines(per_sequence, list(fc.methods), float(fc.get("goal", 0.8)))
          if (fc := cfg.get("flicker_check")) else []),
        *extra_sections(report, cfg.get("extra_evals") or {}, claims, cfg.get("extra_family_metric"), book),
        "## Training runs (steps and best validation PSNR)",
        "",
        markdown_table(runs, ["run", "seed", "steps", "val_psnr", "collapsed"], formats={"val_psnr": ".2f"},
                       headers={"val_psnr": "best val PSNR dB"}).rstrip(),
        "",
    ]
    out = report / "summary.md"
    atomic_write_text(out, "\n".join(lines))
    print(f"wrote {out}")
    return out


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "demo_summary")()


if __name__ == "__main__":
    main()
