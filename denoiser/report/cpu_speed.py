"""The student's speed against OIDN-fast on every CPU the project was measured on: one table.

``denoiser-bench`` writes ``bench.json`` (its machine: CPU model and signature, ISA flags, the fp32
matmul peak, the date and commit; its headline ratios: the student against OIDN-fast, paired per
round, per precision). This module keeps those ratios in a committed CSV, one row per bench run,
size and precision, and renders them as a Markdown table grouped by CPU class:

    python -m denoiser.report.cpu_speed add reports/demo/bench/bench.json [more bench.json ...]
    python -m denoiser.report.cpu_speed render      # docs/results/cpu_speed.md from the CSV

``add`` skips a row already in the CSV (same date, commit, CPU signature, size, method and
median), so adding a file twice changes nothing, and refuses a run made with instruction sets
capped (``isa_caps`` in its machine: :func:`denoiser.machine.isa_caps`); ``render`` only reads the CSV. Timings compare
within a run only (the ratio and its interval come from one run's interleaved rounds); rows of
different runs are different measurements, never merged.

CSV columns (:data:`COLUMNS`): ``date``, ``commit``, ``cpu`` (model name), ``cpu_id``
(``<vendor> family <f> model <m>``), ``cpu_class`` (:func:`cpu_class`), ``threads``, ``size``
(``WxH``), ``student`` (method and backend), ``dtype``, ``student_ms``, ``baseline``,
``baseline_ms``, ``ratio``, ``ratio_lo``, ``ratio_hi`` (the paired median and its interval),
``peak_fraction`` (the student's share of the run's fp32 matmul peak), ``versions``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from denoiser.atomic import atomic_write_text
from denoiser.errors import UserError
from denoiser.tables import IDENTIFIERS, markdown_table, read_csv, write_csv

ROOT = Path(__file__).resolve().parents[2]
#: the committed record and its rendering
CSV = ROOT / "docs" / "results" / "cpu_speed.csv"
MARKDOWN = ROOT / "docs" / "results" / "cpu_speed.md"
COLUMNS = ["date", "commit", "cpu", "cpu_id", "cpu_class", "threads", "size", "student", "dtype", "student_ms",
           "baseline", "baseline_ms", "ratio", "ratio_lo", "ratio_hi", "peak_fraction", "versions"]
#: what makes a row the same measurement (``add`` skips it)
KEY = ("date", "commit", "cpu_id", "size", "student", "student_ms")
#: columns read back as written (a commit hash such as ``0496959`` is not a number)
TEXT = (*IDENTIFIERS, "date", "cpu", "cpu_id", "size", "student", "dtype", "baseline", "versions")


def cpu_class(isa: dict[str, bool]) -> str:
    """The vector class a CPU's timings depend on: ``AMX`` (amx_bf16), ``AVX-512 + BF16``,
    ``AVX-512``, ``AVX2`` or ``other``."""
    if isa.get("amx_bf16"):
        return "AMX"
    if isa.get("avx512f"):
        return "AVX-512 + BF16" if isa.get("avx512_bf16") else "AVX-512"
    return "AVX2" if isa.get("avx2") else "other"


def rows_of_bench(path: Path) -> list[dict]:
    """The CSV rows of one ``bench.json``: one per headline ratio (size and precision)."""
    try:
        bench = json.loads(Path(path).read_text())
        machine, speedups, rows = bench["machine"], bench["speedups"], bench["rows"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a denoiser-bench bench.json ({type(exc).__name__}: {exc})") from None
    if not speedups:
        raise UserError(f"{path}: no student-vs-baseline ratio (the bench timed no student beside OIDN-fast)")
    caps = machine.get("isa_caps") or {}
    if caps:  # denoiser.machine.isa_caps: the run timed another CPU's code paths, and OIDN this one's
        named = ", ".join(f"${k}={v}" for k, v in caps.items())
        raise UserError(f"{path}: ran with instruction sets capped ({named}): its ratio is neither this CPU's nor "
                        "an AVX2 CPU's (OIDN reads no cap), so it is not added to the per-CPU record")
    peak = {(f"{r['method']} ({r['backend']})", f"{r['width']}x{r['height']}"): r.get("peak_fraction")
            for r in rows}
    out = []
    for s in speedups:
        out.append({
            "date": machine.get("date", "unknown"), "commit": machine.get("commit", "unknown"),
            "cpu": machine["cpu"], "cpu_id": machine.get("cpu_id", "unknown"), "cpu_class": cpu_class(machine["isa"]),
            "threads": machine["threads_requested"], "size": s["size"], "student": s["student"], "dtype": s["dtype"],
            "student_ms": round(float(s["student_ms"]), 1), "baseline": s["baseline"],
            "baseline_ms": round(float(s["baseline_ms"]), 1), "ratio": float(s["ratio"]),  # unrounded: the
            "ratio_lo": float(s["ratio_lo"]), "ratio_hi": float(s["ratio_hi"]),  # table rounds once, as the bench
            "peak_fraction": peak.get((s["student"], s["size"])),
            "versions": "; ".join(f"{k} {v}" for k, v in machine.get("versions", {}).items()),
        })
    return out


def add(paths: Sequence[Path], csv: Path = CSV) -> int:
    """Append the rows of each ``bench.json`` in ``paths`` to ``csv`` (rows already there are
    skipped); returns how many were added."""
    new = [row for path in paths for row in rows_of_bench(path)]
    old = read_csv(csv, text=TEXT) if csv.exists() else []
    seen = {tuple(str(r.get(k)) for k in KEY) for r in old}
    added = [r for r in new if tuple(str(r.get(k)) for k in KEY) not in seen]
    if added:
        csv.parent.mkdir(parents=True, exist_ok=True)
        write_csv(csv, old + added, COLUMNS)
    return len(added)


def render(csv: Path = CSV) -> str:
    """The Markdown of ``csv``: per CPU class, its rows (newest first)."""
    rows = read_csv(csv, text=TEXT) if csv.exists() else []
    parts = ["# The student against OIDN-fast, per CPU", "",
             (f"Generated by `python -m denoiser.report.cpu_speed render` from `{csv.name}` (rows added from "
             "`denoiser-bench`'s bench.json by `python -m denoiser.report.cpu_speed add`). Each row is one bench run: "
             "the student and OIDN-fast timed in the same interleaved rounds on the same frames; speed-up = OIDN-fast "
             "ms / student ms, the median of the per-round ratios with its distribution-free interval. Rows of "
             "different runs are different machines or loads: compare ratios, not milliseconds. Of fp32 peak: the "
             "student's GFLOP/s over the run's matmul peak (denoiser.inference.peak.engines_matmul_peak), since 2026-12-02 the "
             "faster of torch.mm and OpenVINO's MatMul; earlier rows took torch.mm alone, whose MKL runs AVX2 code "
             "on AMD CPUs with AVX-512 (so those rows read above 100% on the family 26 EPYC)."), ""]
    for klass in ("AMX", "AVX-512 + BF16", "AVX-512", "AVX2", "other"):
        mine = sorted((r for r in rows if r["cpu_class"] == klass), key=lambda r: (str(r["date"]), str(r["commit"])),
                      reverse=True)
        if not mine:
            continue
        for r in mine:
            r["speedup"] = f"{float(r['ratio']):.2f} ({float(r['ratio_lo']):.2f}-{float(r['ratio_hi']):.2f})"
            r["machine"] = f"{r['cpu']} ({r['cpu_id']})"
            share = r.get("peak_fraction")
            r["peak"] = f"{100 * float(share):.1f}%" if share not in (None, "") else "–"
        parts += [f"## {klass}", "", markdown_table(mine, ["date", "commit", "machine", "threads", "size", "student",
                                                            "dtype", "student_ms", "baseline_ms", "speedup", "peak"],
                                                     {"student_ms": ".1f", "baseline_ms": ".1f"},
                                                     {"student_ms": "student ms", "baseline_ms": "OIDN-fast ms",
                                                      "speedup": "speed-up x (interval)",
                                                      "peak": "of fp32 peak"}), ""]
    return "\n".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m denoiser.report.cpu_speed", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p_add = sub.add_parser("add", help="append the ratios of bench.json files to the CSV, then render")
    p_add.add_argument("bench", nargs="+", type=Path)
    sub.add_parser("render", help=f"write {MARKDOWN.relative_to(ROOT)} from the CSV")
    for p in sub.choices.values():
        p.add_argument("--csv", type=Path, default=CSV)
        p.add_argument("--out", type=Path, default=MARKDOWN)
    args = parser.parse_args(argv)
    try:
        if args.what == "add":
            print(f"{add(args.bench, args.csv)} row(s) added to {args.csv}")
        atomic_write_text(args.out, render(args.csv) + "\n")
        print(f"wrote {args.out}")
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
