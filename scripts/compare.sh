#!/usr/bin/env bash
# `make compare`: the paper's comparison on the demo's held-out scenes -> reports/compare/.
#
#   1. render data/demo_compare (denoiser-render dataset=demo_compare): data/demo's test job with
#      per-sample radiance (save_samples), which ONND reads; frames that exist are kept
#   2. reuse make demo's teacher and distilled students (reports/demo/runs/student_distilled_s<k>;
#      run make demo first) and train the CPU-sized NPPD and WS baselines (net=nppd_demo,
#      net=ws_demo) by the demo student's recipe (experiment=demo_distill: same data, losses,
#      steps and crops, taught by the demo teacher), one run per seed of COMPARE_SEEDS (default "0 1 2")
#   3. denoiser-eval on data/demo_compare's test split: noisy input, OIDN fast/balanced/high, ONND
#      (baselines=compare; COMPARE_ONND=0 leaves it out: baselines=default), teacher, students, NPPD, WS
#   4. denoiser-bench at 1080p (OpenVINO f32 and bf16, eager) for the same methods (networks: first seed;
#      f32 beside bf16: a CPU without bf16 skips bf16, and the students run OpenVINO f32 there)
#   5. summary.md with the Fig. A.2 / A.3 tables and ranking lines (conf/compare_summary.yaml)
# denoiser-train skips a finished run (skip_done=true) and resumes an interrupted one from its
# last.ckpt (ckpt_path=auto; scripts/lib.sh). Stage times: $REPORT/timings.md (a reused run keeps
# the seconds of the run that did it).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
REPORT=reports/compare
RUNS=$REPORT/runs
SEEDS=${COMPARE_SEEDS:-0 1 2}
FIRST=${SEEDS%% *}
BASELINES=compare
[ "${COMPARE_ONND:-1}" = 0 ] && BASELINES=default
mkdir -p "$RUNS"
TIMINGS=$REPORT/timings.md
# shellcheck source=scripts/lib.sh
. scripts/lib.sh
DEMO=reports/$DEMO_RECIPE_NAME/runs   # make demo's runs of the same DEMO_RECIPE
[ -z "$DEMO_REFINE_EXPERIMENT" ] || { echo "error: DEMO_RECIPE=$DEMO_RECIPE: make compare trains beside students distilled by one recipe, and refine fine-tunes them (use demo, tune or motion)" >&2; exit 2; }
[ -f "$DEMO/$DEMO_TEACHER_RUN/DONE" ] || { echo "error: $DEMO/$DEMO_TEACHER_RUN: no finished demo teacher (run make demo first)" >&2; exit 2; }
timings_begin
# its references: data/demo's, copied
stage --reuse "${DENOISER_DATA:-data}/demo_compare" '*.exr' render "$BIN/denoiser-render" dataset=demo_compare \
    "reference_from=${DENOISER_DATA:-data}/demo"
TEACHER=$(best "$DEMO/$DEMO_TEACHER_RUN")
CKPTS="teacher: $TEACHER"
BENCH_CKPTS="teacher: $TEACHER"   # a seed group is timed once (its networks are the same size)
for seed in $SEEDS; do
    student=$DEMO/student_distilled_s$seed
    if [ -f "$student/DONE" ]; then
        CKPTS="$CKPTS, student_s$seed: $(best "$student")"
        [ "$seed" = "$FIRST" ] && BENCH_CKPTS="$BENCH_CKPTS, student_s$seed: $(best "$student")"
    else
        echo "warning: $student: no finished distilled student for seed $seed (make demo DEMO_SEEDS)" >&2
    fi
    for net in nppd_demo ws_demo; do
        dir=$RUNS/${net}_s$seed
        stage --reuse "$dir" DONE "${net}_s$seed" train_run "$dir" "experiment=$DEMO_DISTILL_EXPERIMENT" "net=$net" \
            "model.teacher_ckpt=$TEACHER" "seed=$seed"
        CKPTS="$CKPTS, ${net%_demo}_s$seed: $(best "$dir")"
        [ "$seed" = "$FIRST" ] && BENCH_CKPTS="$BENCH_CKPTS, ${net%_demo}_s$seed: $(best "$dir")"
    done
done
stage eval "$BIN/denoiser-eval" data=demo_compare "baselines=$BASELINES" "ckpt={$CKPTS}" "out_dir=$REPORT/eval" \
    "purpose='make compare: the comparison report'"
stage bench "$BIN/denoiser-bench" data=demo_compare "baselines=$BASELINES" "ckpt={$BENCH_CKPTS}" \
    "eval_csv=$REPORT/eval/metrics.csv" "out_dir=$REPORT/bench" "sizes=[[1080,1920]]" \
    "use_backends=[eager,openvino_f32,openvino_bf16]" "skip={teacher: [[1080,1920]]}" repeats=3 quality=false
stage summary "$PY" -m denoiser.commands.demo_summary --config-name compare_summary "report=$REPORT" "seeds=[${SEEDS// /,}]"
timings_end
echo "==== compare finished: $REPORT/summary.md (Fig. A.2 / A.3 tables), $REPORT/eval/images (crops), $REPORT/bench (plot) ===="
