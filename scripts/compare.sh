#!/usr/bin/env bash
# `make compare`: the paper's comparison on the demo's held-out scenes -> reports/compare/.
#
#   1. reuse make demo's data, teacher and distilled students (run make demo first)
#   2. train the CPU-sized NPPD and WS baselines (net=nppd_demo, net=ws_demo) by the demo
#      student's recipe (experiment=demo_distill: same data, losses, steps and crops, taught by
#      the demo teacher), one run per seed of COMPARE_SEEDS (default "0")
#   3. denoiser-eval on the test split: OIDN (baselines=default, or baselines=compare with ONND
#      when COMPARE_ONND=1 and the data holds per-sample radiance), teacher, student, NPPD, WS
#   4. denoiser-bench at 1080p (OpenVINO bf16 and eager) for the same networks
# Finished runs (DONE) are skipped; an interrupted one resumes from last.ckpt.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
DEMO=reports/demo/runs
REPORT=reports/compare
RUNS=$REPORT/runs
SEEDS=${COMPARE_SEEDS:-0}
BASELINES=default
[ "${COMPARE_ONND:-0}" = 1 ] && BASELINES=compare
mkdir -p "$RUNS"
best() { if [ -f "$1/checkpoints/best.ckpt" ]; then echo "$1/checkpoints/best.ckpt"; else echo "$1/checkpoints/last.ckpt"; fi; }
[ -f "$DEMO/teacher/DONE" ] || { echo "error: $DEMO/teacher: no finished demo teacher (run make demo first)" >&2; exit 2; }
TEACHER=$(best "$DEMO/teacher")
CKPTS="teacher: $TEACHER"
for seed in $SEEDS; do
    [ -f "$DEMO/student_distilled_s$seed/DONE" ] && CKPTS="$CKPTS, student_s$seed: $(best "$DEMO/student_distilled_s$seed")"
    for net in nppd_demo ws_demo; do
        dir=$RUNS/${net}_s$seed
        if [ ! -f "$dir/DONE" ]; then
            resume=(); [ -f "$dir/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
            echo "==> [$net seed $seed]"
            "$PY" train.py experiment=demo_distill "net=$net" "model.teacher_ckpt=$TEACHER" "seed=$seed" \
                "hydra.run.dir=$dir" "${resume[@]}"
            touch "$dir/DONE"
        fi
        CKPTS="$CKPTS, ${net%_demo}_s$seed: $(best "$dir")"
    done
done
"$BIN/denoiser-eval" data=demo "baselines=$BASELINES" "ckpt={$CKPTS}" "out_dir=$REPORT/eval"
FIRST=${SEEDS%% *}
"$BIN/denoiser-bench" data=demo "baselines=$BASELINES" "ckpt={$CKPTS}" "eval_csv=$REPORT/eval/metrics.csv" \
    "out_dir=$REPORT/bench" "sizes=[[1080,1920]]" "use_backends=[eager,openvino_bf16]" "skip={teacher: [[1080,1920]]}" \
    repeats=3 quality=false
"$PY" -m denoiser.commands.demo_summary "report=$REPORT" "seeds=[${SEEDS// /,}]"
echo "==== compare finished: $REPORT/summary.md (tables), $REPORT/eval/images (crops), $REPORT/bench (plot) ===="
