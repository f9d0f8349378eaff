#!/usr/bin/env bash
# `make paper`: the paper's figures on the current code and recipe, after make demo, in order:
#
#   1. ablations  scripts/ablations.sh: Fig. A.1 (the pyramid) and the distillation ablations
#                 -> reports/ablations/summary.md
#   2. compare    scripts/compare.sh: Fig. A.2 / A.3 -> reports/compare/summary.md
#   3. pareto     scripts/pareto.sh: the accuracy-vs-time Pareto front -> reports/pareto/pareto.md
#
# Every stage reuses make demo's data and teacher (this script stops with one line when the
# teacher is missing: make pareto alone would train a shorter one) and is resumable on its own,
# so a second make paper redoes only what is missing or changed. Each stage's wall time goes to
# reports/paper/timings.md (as make demo's reports/demo_refine/timings.md), and each stage keeps its own table of
# steps (reports/<stage>/timings.md, the seconds of reused steps kept); scripts/paper_summary.py
# adds up their work against the budget -> reports/paper/summary.md. The Makefile then copies the
# reports' blocks into the README (make readme-ablations, readme-compare, readme-pareto, readme-paper).
# Knobs: those of the three scripts (ABLATION_*, COMPARE_*, PARETO_*).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
REPORT=reports/paper
TIMINGS=$REPORT/timings.md
TEACHER=reports/demo/runs/teacher
[ -f "$TEACHER/DONE" ] || { echo "error: $TEACHER: no finished demo teacher (run make demo first)" >&2; exit 2; }
mkdir -p "$REPORT"
# shellcheck source=scripts/lib.sh
. scripts/lib.sh
timings_begin
for name in ablations compare pareto; do stage "$name" bash "scripts/$name.sh"; done
timings_end
"$PY" scripts/paper_summary.py --paper "$TIMINGS" --out "$REPORT/summary.md"
echo "==== paper finished: reports/ablations, reports/compare, reports/pareto; stage timings: $TIMINGS ===="
cat "$TIMINGS"
