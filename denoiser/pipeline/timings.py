"""The stage-time table of a pipeline run: ``<report>/timings.md``, one row per stage.

The table is markdown, ``| stage | seconds | run |``, the stages in the order they ran (jobs run
side by side are one stage, their wall time). A stage whose work an earlier run did (finished
training runs skipped, frames kept, an evaluation of the same checkpoints) keeps the seconds of
the run that did it and names that run, so a resumed pipeline's table still says what its work
costs. Two rows close the table: ``total`` (this run's wall time) and ``work`` (the sum of every
stage's seconds: the wall time of a run that reused nothing). The table is written to
``timings.md.tmp`` as the run goes and becomes ``timings.md`` when it ends, so an interrupted run
leaves the last complete table in place.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

HEADER = "| stage | seconds | run |\n|---|---:|---|\n"


def read_rows(path: Path) -> dict[str, tuple[int, str]]:
    """``{stage: (seconds, run)}`` of a table (``total`` and ``work`` left out); a table from
    before the run column names ``an earlier run``. A missing file reads as no rows."""
    rows: dict[str, tuple[int, str]] = {}
    if not path.is_file():
        return rows
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not cells[1].isdigit() or cells[0] in ("total", "work"):
            continue
        rows[cells[0]] = (int(cells[1]), cells[2] if len(cells) > 2 and cells[2] else "an earlier run")
    return rows


def newest(path: Path) -> Path | None:
    """The table a reader should take: ``<path>.tmp`` (a run writing it: a stage of that very run,
    a summary, reads the stages before it) when it is newer than ``path`` (the last complete table),
    else ``path``; None when neither exists."""
    path = Path(path)
    found = [p for p in (path.with_name(path.name + ".tmp"), path) if p.is_file()]
    return max(found, key=lambda p: p.stat().st_mtime_ns) if found else None


@dataclass
class TimingTable:
    """The table of one pipeline run at ``path`` (begun on construction, written by :meth:`end`)."""

    path: Path
    run: str = field(default_factory=lambda: "run " + datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))
    clock: callable = time.monotonic

    def __post_init__(self):
        self.path = Path(self.path)
        self.before = read_rows(self.path)
        self.rows: list[tuple[str, int, str]] = []
        self.start = self.clock()
        self._write(self.path.with_name(self.path.name + ".tmp"))

    def add(self, stage: str, seconds: float, reused: bool = False) -> tuple[int, str]:
        """A row of this run, or (``reused``) the last table's row of ``stage``: the seconds and the
        run that did the work (this run's seconds when the last table has none). Returns the row."""
        if reused and stage in self.before:
            row = self.before[stage]
        elif reused:
            row = (round(seconds), "reused (the run that did it is not recorded)")
        else:
            row = (round(seconds), self.run)
        self.rows.append((stage, *row))
        self._write(self.path.with_name(self.path.name + ".tmp"))
        return row

    @property
    def work(self) -> int:
        return sum(seconds for _, seconds, _ in self.rows)

    def end(self) -> Path:
        """Add the ``total`` and ``work`` rows and put the table in place."""
        self.total = round(self.clock() - self.start)
        tmp = self.path.with_name(self.path.name + ".tmp")
        self._write(tmp, closing=True)
        os.replace(tmp, self.path)
        return self.path

    def _write(self, path: Path, closing: bool = False) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        lines = [HEADER]
        lines += [f"| {stage} | {seconds} | {run} |\n" for stage, seconds, run in self.rows]
        if closing:
            lines.append(f"| total | {self.total} | {self.run}: wall time |\n")
            lines.append(f"| work | {self.work} | every stage's seconds, reused ones included |\n")
        path.write_text("".join(lines))
