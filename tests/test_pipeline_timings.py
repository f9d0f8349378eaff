"""Stage times of the pipeline scripts (scripts/lib.sh: timings_begin, stage, timings_row,
timings_end) and make paper's budget (scripts/paper_summary.py): a resumed pipeline's table keeps
the seconds of the run that did a reused step, and the budget adds up the stages' work."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def pipeline(tmp_path: Path, body: str) -> str:
    """Run ``body`` in bash after sourcing scripts/lib.sh, in ``tmp_path``; its table's text."""
    script = f"""set -euo pipefail
cd {tmp_path}
TIMINGS={tmp_path}/timings.md
. {ROOT}/scripts/lib.sh
timings_begin
{body}
timings_end
"""
    subprocess.run(["bash", "-c", script], check=True, capture_output=True, text=True)
    return (tmp_path / "timings.md").read_text()


def rows(table: str) -> dict[str, list[str]]:
    out = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out


def test_a_reused_step_keeps_the_seconds_of_the_run_that_did_it(tmp_path):
    train = 'mkdir -p runs/a && { [ -f runs/a/DONE ] || { sleep 1; touch runs/a/DONE; }; }'
    first = rows(pipeline(tmp_path, f"stage --reuse runs/a DONE a bash -c '{train}'\nstage b true"))
    assert first["a"][0] == "1" and first["a"][1].startswith("run ") and first["b"][0] == "0"
    assert first["work"][0] == "1" and first["total"][1].endswith("wall time")
    # the second run finds a finished: it wrote no DONE, so the row is the first run's
    second = rows(pipeline(tmp_path, f"stage --reuse runs/a DONE a bash -c '{train}'\nstage b true\ntimings_row e 0 reused"))
    assert second["a"] == first["a"]  # the same seconds and the same run named
    this_run = second["total"][1].removesuffix(": wall time")
    assert this_run != first["a"][1] and second["b"][1] == this_run  # a step without --reuse: this run's
    assert second["e"][1].startswith("reused") and second["work"][0] == "1"
    # a redone step is this run's again
    (tmp_path / "runs" / "a" / "DONE").unlink()
    third = rows(pipeline(tmp_path, f"stage --reuse runs/a DONE a bash -c '{train}'"))
    assert third["a"][0] == "1" and third["a"][1] == third["total"][1].removesuffix(": wall time")


def test_a_table_from_before_the_run_column_is_carried_over(tmp_path):
    (tmp_path / "runs" / "a").mkdir(parents=True)
    (tmp_path / "runs" / "a" / "DONE").touch()
    (tmp_path / "timings.md").write_text("| stage | seconds |\n|---|---|\n| a | 731 |\n| total | 900 |\n")
    table = rows(pipeline(tmp_path, "stage --reuse runs/a DONE a true"))
    assert table["a"] == ["731", "an earlier run"] and table["work"][0] == "731"


def paper_summary(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "paper_summary.py"), "--paper",
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
    proc = paper_summary(tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "summary.md").read_text()
    block = text.split("<!-- paper:begin -->")[1].split("<!-- paper:end -->")[0]
    table = rows("\n".join(line for line in block.splitlines() if line.startswith("|")))
    assert table["ablations"][:3] == ["650", "0.18 h", "95"]      # an old table: its total row
    assert table["compare"][:3] == ["3600", "1.00 h", "3600"]     # no table: make paper's row
    assert table["pareto"][:3] == ["2900", "0.81 h", "3000"]      # its work row
    assert table["all"][:3] == ["7150", "1.99 h", "6700"]
    assert "within the budget of 2.00 h" in block and "- commit: " in text and "- run id: " in text
    proc = paper_summary(tmp_path, "--budget-hours", "1")
    assert "over the budget of 1.00 h by 0.99 h (2.0x)" in (tmp_path / "summary.md").read_text()
    (tmp_path / "paper.md").write_text("| stage | seconds |\n|---|---|\n| ablations | 95 |\n")
    proc = paper_summary(tmp_path)
    assert proc.returncode == 1 and "no row for stage(s) compare, pareto" in proc.stderr
