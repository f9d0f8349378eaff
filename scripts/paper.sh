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
# reports/paper/timings.md (as reports/demo/timings.md); the Makefile then copies the reports'
# blocks into the README (make readme-ablations, make readme-pareto).
# Knobs: those of the three scripts (ABLATION_*, COMPARE_*, PARETO_*).
set -euo pipefail
cd "$(dirname "$0")/.."

REPORT=reports/paper
TIMINGS=$REPORT/timings.md
TEACHER=reports/demo/runs/teacher
[ -f "$TEACHER/DONE" ] || { echo "error: $TEACHER: no finished demo teacher (run make demo first)" >&2; exit 2; }
mkdir -p "$REPORT"
printf '| stage | seconds |\n|---|---|\n' > "$TIMINGS.tmp"
START=$(date +%s)
for stage in ablations compare pareto; do
    t0=$(date +%s)
    echo "==> [paper: $stage] scripts/$stage.sh"
    bash "scripts/$stage.sh"
    echo "| $stage | $(( $(date +%s) - t0 )) |" >> "$TIMINGS.tmp"
done
echo "| total | $(( $(date +%s) - START )) |" >> "$TIMINGS.tmp"
mv "$TIMINGS.tmp" "$TIMINGS"
echo "==== paper finished: reports/ablations, reports/compare, reports/pareto; stage timings: $TIMINGS ===="
cat "$TIMINGS"
