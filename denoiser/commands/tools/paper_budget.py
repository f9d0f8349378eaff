"""The budget of ``make paper``: what each stage's work costs, from the stage tables the pipelines
wrote, against the budget -> ``reports/paper/summary.md`` (``make readme`` copies its block):
``python -m denoiser.commands.tools.paper_budget``.

A stage's work is the ``work`` row of its own table (``reports/<stage>/timings.md``: every step's
seconds, the steps that an earlier run did included, with the seconds of that run; ``denoiser/pipeline/timings.py``),
or its ``total`` row when the table has no ``work`` row (a table from before the row existed, whose
run did the work: its rows, runs side by side, add up to more than its wall time);
a stage without a table counts its wall time in ``make paper``'s own table
(``reports/paper/timings.md``, or ``timings.md.tmp`` when newer: the table of the make paper whose
last stage this summary is). So a ``make paper`` that resumed work done earlier still states
what the whole work costs, and how long this run took beside it.

Below the budget's block, the summary holds each stage's own results block (the text between
``<!-- <stage>:begin -->`` and ``<!-- <stage>:end -->`` of ``reports/<stage>/summary.md``, the Pareto
front's ``reports/pareto/pareto.md``), with that file's run id and commit and its pictures linked, so
one file covers Fig. A.1 and the ablations, A.2/A.3 and the front; ``make readme`` copies each block
into ``docs/results.md`` from its own file.

Usage::

    python -m denoiser.commands.tools.paper_budget [--paper reports/paper/timings.md] [--reports reports] \\
        [--stages ablations,compare,pareto] [--budget-hours 6] [--out reports/paper/summary.md]

``key=value`` arguments (``budget_hours=6``) are accepted as well as ``--key value``. A missing
table or a stage without a row in it is one line ``error: ...`` on stderr and exit 2.
"""

from __future__ import annotations

import csv
import datetime
import os
import re
import sys
from pathlib import Path

from denoiser.atomic import atomic_write_text
from denoiser.commands.app import CommandParser, report_user_error
from denoiser.errors import UserError
from denoiser.machine import cpu_model
from denoiser.pipeline.timings import newest
from denoiser.report.provenance import git_commit

BEGIN, END = "<!-- paper:begin -->", "<!-- paper:end -->"


def read_table(path: Path) -> dict[str, int]:
    """``{stage: seconds}`` of a stage-time table (``| stage | seconds | ... |`` rows; the header,
    separator and non-numeric rows skipped)."""
    rows = {}
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and cells[1].isdigit():
            rows[cells[0]] = int(cells[1])
    return rows


def stage_work(table: dict[str, int]) -> int:
    """A stage table's work: its ``work`` row, else (a table from before the row existed, written
    by a run that did all of the work) its ``total`` row, else the sum of its rows."""
    for row in ("work", "total"):
        if row in table:
            return table[row]
    return sum(table.values())


REPORT_FILES = {"pareto": "pareto.md"}  # a stage's results file in reports/<stage>/ (default summary.md)
IMAGE = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)\)")


def stage_section(name: str, reports: Path, out_dir: Path) -> list[str]:
    """The lines of stage ``name``'s section: its results file's run id and commit, its block
    (between the ``name`` markers) and its pictures, linked from ``out_dir``."""
    path = reports / name / REPORT_FILES.get(name, "summary.md")
    if not path.is_file():
        raise UserError(f"{path}: not found (the {name} stage's results; run make paper)")
    text = path.read_text()
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    if begin not in text or end not in text.split(begin, 1)[1]:
        raise UserError(f"{path}: no {begin} ... {end} block")
    block = text.split(begin, 1)[1].split(end, 1)[0].strip("\n")
    header = [line for line in text.splitlines() if line.startswith(("- run id:", "- commit:"))][:2]
    rel = Path(os.path.relpath(path.parent, out_dir)).as_posix()
    pictures = [f"![{m.group(1)}]({rel}/{m.group(2)})" for m in IMAGE.finditer(text)
                if "://" not in m.group(2) and not m.group(2).startswith("/")]
    lines = ["", f"## {name}: `{path.as_posix()}`", "", *header, "", block]
    if name == "pareto" and (path.parent / "pareto.csv").is_file():
        with open(path.parent / "pareto.csv", newline="") as f:
            trained = sum(row.get("kind") == "network" for row in csv.DictReader(f))
        lines += ["", f"Trained points of the front's sweep: {trained} (`{(path.parent / 'pareto.csv').as_posix()}`)."]
    return lines + ([""] + pictures if pictures else [])


def hours(seconds: int) -> str:
    return f"{seconds / 3600:.2f} h"


def summary(paper: Path, stages: list[str], reports: Path, budget_hours: float, out_dir: Path = Path(".")) -> str:
    """The summary's text (module docstring); pictures linked from ``out_dir``."""
    table = newest(paper)
    if table is None:
        raise UserError(f"{paper}: not found (run make paper first)")
    walls = read_table(table)
    missing = [s for s in stages if s not in walls]
    if missing:
        raise UserError(f"{table}: no row for stage(s) {', '.join(missing)}")
    rows, total_work = [], 0
    for name in stages:
        own = reports / name / "timings.md"
        if own.is_file():
            work, source = stage_work(read_table(own)), f"`{own}`"
        else:
            work, source = walls[name], f"`{paper}` (the stage keeps no table)"
        total_work += work
        rows.append(f"| {name} | {work} | {hours(work)} | {walls[name]} | {source} |")
    budget = round(budget_hours * 3600)
    verdict = (f"within the budget of {hours(budget)}" if total_work <= budget
               else f"over the budget of {hours(budget)} by {hours(total_work - budget)} ({total_work / budget:.1f}x)")
    run_id = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return "\n".join([
        "# make paper: the work of every stage, against the budget", "",
        f"- run id: {run_id}",
        f"- commit: {git_commit()}",
        f"- stages: {', '.join(stages)} (conf/pipeline/paper.yaml)", "",
        BEGIN,
        "| stage | work, s | work | wall time in the last make paper, s | from |",
        "|---|---:|---:|---:|---|",
        *rows,
        f"| all | {total_work} | {hours(total_work)} | {walls.get('total', sum(walls[s] for s in stages))} | |",
        "",
        (f"Work: every step's wall time in the run that did it (a step a later run reused keeps that "
         f"run's seconds; denoiser/pipeline/timings.py). All of it takes {hours(total_work)} on this machine "
         f"({cpu_model()}, {os.cpu_count()} cores), {verdict}."),
        END,
        *[line for name in stages for line in stage_section(name, reports, out_dir)], ""])


def main(argv=None) -> int:
    parser = CommandParser("denoiser.commands.tools.paper_budget", __doc__)
    parser.add_argument("--paper", type=Path, default=Path("reports/paper/timings.md"),
                        help="make paper's own stage table (default reports/paper/timings.md)")
    parser.add_argument("--reports", type=Path, default=Path("reports"),
                        help="where the stages' own tables are, <reports>/<stage>/timings.md (default reports)")
    parser.add_argument("--stages", default="ablations,compare,pareto",
                        help="comma-separated stages (default ablations,compare,pareto)")
    parser.add_argument("--budget-hours", type=float, default=6.0,
                        help="the budget in hours (default 6: issue 47's, 2 idle cores after make demo)")
    parser.add_argument("--out", type=Path, default=Path("reports/paper/summary.md"),
                        help="the summary written (default reports/paper/summary.md)")
    args = parser.parse_args(argv)
    try:
        stages = [s for s in args.stages.split(",") if s]
        if not stages:
            raise UserError("stages: empty (e.g. stages=ablations,compare,pareto)")
        if not args.budget_hours > 0:
            raise UserError(f"budget_hours: {args.budget_hours} is not a positive number of hours")
        text = summary(args.paper, stages, args.reports, args.budget_hours, args.out.parent)
        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(args.out, text)
        except OSError as e:
            raise UserError(f"{args.out}: cannot write: {e.strerror or e}") from None
    except UserError as e:
        report_user_error(e)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
