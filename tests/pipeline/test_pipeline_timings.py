"""Stage times of the pipelines (denoiser/pipeline/timings.py) and make paper's budget (denoiser/commands/tools/paper_budget.py): a resumed pipeline's table keeps
the seconds of the run that did a reused step, and the budget adds up the stages' work."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class Clock:
    """A clock the test moves by hand (seconds)."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def rows(table: str) -> dict[str, list[str]]:
    out = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out


def test_a_reused_step_keeps_the_seconds_of_the_run_that_did_it(tmp_path):
    from denoiser.pipeline.timings import TimingTable

    path, clock = tmp_path / "timings.md", Clock()
    first = TimingTable(path, run="run one", clock=clock)
    assert (tmp_path / "timings.md.tmp").is_file() and not path.exists()  # the table of a finished run only
    clock.now = 1
    first.add("a", 1)
    first.add("b", 0)
    first.end()
    one = rows(path.read_text())
    assert one["a"] == ["1", "run one"] and one["b"] == ["0", "run one"]
    assert one["work"][0] == "1" and one["total"] == ["1", "run one: wall time"]
    # the second run reused a: the row is the first run's; b without reuse and e with no row before
    second = TimingTable(path, run="run two", clock=Clock())
    second.add("a", 0, reused=True)
    second.add("b", 0)
    second.add("e", 0, reused=True)
    second.end()
    two = rows(path.read_text())
    assert two["a"] == one["a"] and two["b"] == ["0", "run two"]
    assert two["e"][1].startswith("reused") and two["work"][0] == "1"
    # a redone step is this run's again
    third = TimingTable(path, run="run three", clock=Clock())
    third.add("a", 2)
    third.end()
    assert rows(path.read_text())["a"] == ["2", "run three"]


def test_a_table_from_before_the_run_column_is_carried_over(tmp_path):
    from denoiser.pipeline.timings import TimingTable

    (tmp_path / "timings.md").write_text("| stage | seconds |\n|---|---|\n| a | 731 |\n| total | 900 |\n")
    table = TimingTable(tmp_path / "timings.md", clock=Clock())
    table.add("a", 0, reused=True)
    table.end()
    assert rows((tmp_path / "timings.md").read_text())["a"] == ["731", "an earlier run"]
    assert rows((tmp_path / "timings.md").read_text())["work"][0] == "731"


def paper_budget(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "denoiser.commands.tools.paper_budget", "--paper",
                           str(tmp_path / "paper.md"), "--reports", str(tmp_path / "reports"), "--out",
                           str(tmp_path / "summary.md"), *args], capture_output=True, text=True, check=False)


def test_paper_summary_adds_up_the_stages_work_against_the_budget(tmp_path):
    (tmp_path / "paper.md").write_text("| stage | seconds | run |\n|---|---:|---|\n| ablations | 95 | run x |\n"
                                       "| compare | 3600 | run x |\n| pareto | 3000 | run x |\n| total | 6700 | run x |\n")
    (tmp_path / "reports" / "ablations").mkdir(parents=True)
    (tmp_path / "reports" / "ablations" / "timings.md").write_text(   # an old table: no work row
        "| stage | seconds |\n|---|---|\n| k3_s0 | 500 |\n| eval | 100 |\n| total | 650 |\n")
    (tmp_path / "reports" / "pareto").mkdir()
    (tmp_path / "reports" / "pareto" / "timings.md").write_text(
        "| stage | seconds | run |\n|---|---:|---|\n| sweep | 2000 | run y |\n| total | 2100 | run y: wall time |\n"
        "| work | 2900 | every stage's seconds |\n")
    proc = paper_budget(tmp_path)
    assert proc.returncode == 2 and proc.stderr == (   # the stages' results are part of the summary
        f"error: {tmp_path / 'reports' / 'ablations' / 'summary.md'}: not found (the ablations stage's results; run make paper)\n")
    for name, file in (("ablations", "summary.md"), ("compare", "summary.md"), ("pareto", "pareto.md")):
        (tmp_path / "reports" / name).mkdir(exist_ok=True)
        (tmp_path / "reports" / name / file).write_text(
            f"# {name}\n\n- run id: R-{name}\n- commit: C-{name}\n\n<!-- {name}:begin -->\n| {name} table |\n"
            f"<!-- {name}:end -->\n\n![{name} picture]({name}.png)\n")
    (tmp_path / "reports" / "pareto" / "pareto.csv").write_text("job,kind\n0,network\n1,network\noidn,baseline\n")
    proc = paper_budget(tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "summary.md").read_text()
    for name, file in (("ablations", "summary.md"), ("compare", "summary.md"), ("pareto", "pareto.md")):
        section = text.split(f"## {name}: ")[1]
        assert f"- run id: R-{name}\n- commit: C-{name}\n\n| {name} table |" in section
        assert f"![{name} picture](reports/{name}/{name}.png)" in section.split("## ")[0]   # linked from where summary.md is
    assert "Trained points of the front's sweep: 2" in text
    block = text.split("<!-- paper:begin -->")[1].split("<!-- paper:end -->")[0]
    table = rows("\n".join(line for line in block.splitlines() if line.startswith("|")))
    assert table["ablations"][:3] == ["650", "0.18 h", "95"]      # an old table: its total row
    assert table["compare"][:3] == ["3600", "1.00 h", "3600"]     # no table: make paper's row
    assert table["pareto"][:3] == ["2900", "0.81 h", "3000"]      # its work row
    assert table["all"][:3] == ["7150", "1.99 h", "6700"]
    assert "within the budget of 6.00 h" in block and "- commit: " in text and "- run id: " in text  # the default budget
    proc = paper_budget(tmp_path, "--budget-hours", "1")
    assert "over the budget of 1.00 h by 0.99 h (2.0x)" in (tmp_path / "summary.md").read_text()
    (tmp_path / "paper.md").write_text("| stage | seconds |\n|---|---|\n| ablations | 95 |\n")
    proc = paper_budget(tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("error: ") and "no row for stage(s) compare, pareto" in proc.stderr
    proc = paper_budget(tmp_path, "budget_hours=lots")   # key=value, a bad value: one line too
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "budget-hours" in proc.stderr


def test_a_reader_takes_the_running_table_only_when_it_is_newer_than_the_last_complete_one(tmp_path):
    from denoiser.pipeline.timings import TimingTable, newest

    assert newest(tmp_path / "timings.md") is None
    table = TimingTable(tmp_path / "timings.md", clock=Clock())
    assert newest(tmp_path / "timings.md") == tmp_path / "timings.md.tmp"     # a run going: its table
    table.add("a", 3)
    table.end()
    assert newest(tmp_path / "timings.md") == tmp_path / "timings.md"         # ended: the complete one
    stale = tmp_path / "timings.md.tmp"
    stale.write_text("| stage | seconds | run |\n|---|---:|---|\n")
    os.utime(stale, ns=(1, 1))                                                 # an interrupted run's, older
    assert newest(tmp_path / "timings.md") == tmp_path / "timings.md"
