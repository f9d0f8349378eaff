#!/usr/bin/env bash
# `make ablations`: the paper's Fig. A.1 (the pyramid) and its distillation ablations on the demo's
# held-out scenes -> reports/ablations/summary.md (docs/training.md, "make ablations").
#
#   1. reuse make demo's data (data/demo), teacher (reports/demo/runs/teacher) and students: its
#      distilled students student_distilled_s<k> are the full recipe (variant `none`, the pyramid
#      student) and its students on references alone student_no_kd_s<k> are `no_kd`; nothing of
#      them is retrained (run make demo first: without them this stops with one line)
#   2. train every other variant, one run per seed of ABLATION_SEEDS: the demo student's recipe
#      with one ablation (denoiser-train experiment=demo_distill model.teacher_ckpt=<demo teacher>
#      ablation=<variant> seed=<k>, the same steps as make demo's students) into
#      reports/ablations/runs/<variant>_s<k>, ABLATION_JOBS runs side by side with ABLATION_THREADS
#      torch threads each. Variants: Fig. A.1's no_pyramid (one full-resolution kernel) and direct
#      (the U-Net predicts the color), the distillation's no_unlabeled, no_adversarial,
#      no_param_transfer, and the kernel sizes k3 and k7 (conf/ablation/<variant>.yaml)
#   3. denoiser-eval of every run (best.ckpt, else last.ckpt) on data/demo's test split, with the
#      noisy input; crop images of the same frame of none, no_pyramid and direct (seed: the first)
#   4. denoiser-bench at 1920x1080 of the Fig. A.1 networks (first seed) with OIDN-fast on
#      OpenVINO f32 and bf16 (eager when OpenVINO is not installed; ABLATION_BACKENDS)
#   5. python -m denoiser.commands.ablation_summary: the tables, paired intervals against `none`
#      and one sentence per claim of the paper (holds or not), the crop figure (crops_a1.png)
#
# Resumable: denoiser-train skips a finished run (skip_done=true: DONE in its directory) and
# resumes an interrupted one from its last.ckpt (ckpt_path=auto); the evaluation and the benchmark
# are redone only when their checkpoints changed (inputs.txt in their directory). A run that
# collapses is kept and marked in the summary (it is a result of its ablation), a run that fails
# stops the script (its log: reports/ablations/runs/<run>.log).
# Knobs (environment): ABLATION_SEEDS (default "0 1 2"; make demo's students must have them),
# ABLATION_JOBS (default 2), ABLATION_THREADS (torch threads per run, default 1; JOBS x THREADS
# <= cores), ABLATION_STEPS (default empty: the recipe's own trainer.max_steps, as make demo's
# students; another value makes the comparison unequal, the summary says so), ABLATION_VARIANTS
# (default all of step 2; a subset of them), ABLATION_BACKENDS (a denoiser-bench use_backends list), ABLATION_REPEATS
# (timed rounds, default 7).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
DATA=${DENOISER_DATA:-data}/demo
REPORT=reports/ablations
RUNS=$REPORT/runs
SEEDS=${ABLATION_SEEDS:-0 1 2}
FIRST=${SEEDS%% *}
JOBS=${ABLATION_JOBS:-2}
THREADS=${ABLATION_THREADS:-1}
STEPS=${ABLATION_STEPS:-}
VARIANTS=${ABLATION_VARIANTS:-no_pyramid direct no_unlabeled no_adversarial no_param_transfer k3 k7}
VARIANTS=$(for v in $VARIANTS; do [ "$v" = none ] || [ "$v" = no_kd ] || printf '%s ' "$v"; done)  # make demo's
REPEATS=${ABLATION_REPEATS:-7}
mkdir -p "$RUNS"
TIMINGS=$REPORT/timings.md
# shellcheck source=scripts/lib.sh
. scripts/lib.sh
DEMO=reports/$DEMO_RECIPE_NAME/runs   # make demo's runs of the same DEMO_RECIPE
[ -z "$DEMO_REFINE_EXPERIMENT" ] || { echo "error: DEMO_RECIPE=$DEMO_RECIPE: make ablations trains beside students distilled by one recipe, and refine fine-tunes them (use demo, tune or motion)" >&2; exit 2; }
need() {  # need <path> <what>: stop with one line naming make demo when it is missing
    [ -e "$1" ] || { echo "error: $1: $2 missing (run make demo first)" >&2; exit 2; }
}
run_dir() {  # the run directory of <variant> <seed>: make demo's for none and no_kd
    case $1 in
        none) echo "$DEMO/student_distilled_s$2" ;;
        no_kd) echo "$DEMO/student_no_kd_s$2" ;;
        *) echo "$RUNS/$1_s$2" ;;
    esac
}

need "$DATA/test" "the demo's test split"
need "$DEMO/$DEMO_TEACHER_RUN/DONE" "the finished demo teacher"
for seed in $SEEDS; do
    need "$DEMO/student_distilled_s$seed/DONE" "make demo's distilled student of seed $seed (DEMO_SEEDS)"
    need "$DEMO/student_no_kd_s$seed/DONE" "make demo's no-KD student of seed $seed (DEMO_SEEDS)"
done
TEACHER=$(best "$DEMO/$DEMO_TEACHER_RUN")   # the checkpoint make demo's distilled students were taught by
timings_begin

train() {  # train <variant>_s<seed>: one run, its output in <run>.log
    local name=$1 variant=${1%_s*} seed=${1##*_s} t0=$SECONDS
    echo "==> [$name]"
    OMP_NUM_THREADS=$THREADS train_run "$RUNS/$name" "experiment=$DEMO_DISTILL_EXPERIMENT" "model.teacher_ckpt=$TEACHER" \
        "ablation=$variant" "seed=$seed" ${STEPS:+"trainer.max_steps=$STEPS"} \
        trainer.enable_progress_bar=false callbacks.progress=null > "$RUNS/$name.log" 2>&1 \
        || { echo "error: [$name] failed, see $RUNS/$name.log" >&2; return 1; }
    [ -f "$RUNS/$name/COLLAPSED" ] && echo "warning: [$name] $(cat "$RUNS/$name/COLLAPSED") (kept, marked in the summary)" >&2
    echo "<== [$name] $(( SECONDS - t0 ))s"
}
NAMES=()
for variant in $VARIANTS; do for seed in $SEEDS; do NAMES+=("${variant}_s$seed"); done; done
# one row for the runs, JOBS side by side (their wall time, not the sum of theirs)
stage --reuse "$RUNS" DONE train run_jobs "$JOBS" train "${NAMES[@]}" || exit 3

CKPTS=""
SHOWN="'noisy input'"   # the crop images: the same frame of Fig. A.1's networks
for variant in none no_kd $VARIANTS; do
    for seed in $SEEDS; do CKPTS="$CKPTS${CKPTS:+, }${variant}_s$seed: $(best "$(run_dir "$variant" "$seed")")"; done
done
BENCH_CKPTS=""
for variant in none no_pyramid direct; do
    [ "$variant" = none ] || [[ " $VARIANTS " == *" $variant "* ]] || continue
    SHOWN="$SHOWN,${variant}_s$FIRST"
    BENCH_CKPTS="$BENCH_CKPTS${BENCH_CKPTS:+, }${variant}_s$FIRST: $(best "$(run_dir "$variant" "$FIRST")")"
done
if fresh "$REPORT/eval" "$CKPTS"; then
    echo "==> [eval] $REPORT/eval: the same checkpoints, done before"
    timings_row eval 0 reused
else
    stage eval "$BIN/denoiser-eval" data=demo "ckpt={$CKPTS}" "out_dir=$REPORT/eval" '~baselines.oidn_fast' \
        "purpose='make ablations: the ablation report'" \
        '~baselines.oidn_balanced' '~baselines.oidn_high' "images.methods=[$SHOWN]"
    echo "$CKPTS" > "$REPORT/eval/inputs.txt"
fi

BACKENDS=${ABLATION_BACKENDS:-}
if [ -z "$BACKENDS" ]; then
    if "$PY" -c 'import openvino' 2> /dev/null; then BACKENDS="[openvino_f32,openvino_bf16]"
    else BACKENDS="[eager]"; echo "note: OpenVINO is not installed: timing on eager" >&2; fi
fi
if fresh "$REPORT/bench" "$BENCH_CKPTS $BACKENDS $REPEATS"; then
    echo "==> [bench] $REPORT/bench: the same checkpoints and backends, done before"
    timings_row bench 0 reused
else
    stage bench "$BIN/denoiser-bench" data=demo "ckpt={$BENCH_CKPTS}" "eval_csv=$REPORT/eval/metrics.csv" \
        "out_dir=$REPORT/bench" "sizes=[[1080,1920]]" "use_backends=$BACKENDS" '~baselines.oidn_balanced' \
        '~baselines.oidn_high' quality=false check_oidn=false "repeats=$REPEATS" "compare.student=none_s$FIRST"
    echo "$BENCH_CKPTS $BACKENDS $REPEATS" > "$REPORT/bench/inputs.txt"
fi

REPORTED=$(echo none no_kd $VARIANTS | tr ' ' ,)
stage summary "$PY" -m denoiser.commands.ablation_summary "report=$REPORT" "data_root=$DATA" \
    "seeds=[${SEEDS// /,}]" "variants=[$REPORTED]" "teacher=$TEACHER"
timings_end

cat <<EOF

==== ablations finished: $REPORT/ ====
  summary            $REPORT/summary.md   (README block: make readme-ablations)
  crop figure        $REPORT/crops_a1.png   (every test sequence: $REPORT/eval/images/)
  per sequence       $REPORT/eval/metrics.csv
  1080p times        $REPORT/bench/report.md
  TensorBoard        tensorboard --logdir $RUNS
  stage timings      $TIMINGS
EOF
