#!/usr/bin/env bash
# `make demo`: the whole pipeline on the small simulated demo dataset, on the CPU.
#
#   1. render data/demo (denoiser-render dataset=demo; frames that exist are kept: cached)
#   2. train the demo teacher                 (experiment=demo_teacher)
#   3. distill the demo student               (experiment=demo_distill, teacher from step 2)
#   4. train the same student without KD      (experiment=demo_distill ablation=no_kd), for as
#      many steps as the distilled student made
#   5. evaluate noisy input, OIDN, teacher, both students on the held-out test sequences
#      (denoiser-eval) and time them (denoiser-bench)
#   6. write reports/demo/: metrics table, accuracy-vs-time plot, PNG crops, TensorBoard logs
#
# Every stage is skipped when its result exists (a finished run leaves DONE in its directory;
# an interrupted one resumes from its last.ckpt). DEMO_FRESH=1 retrains everything.
# Knobs (environment): DEMO_THREADS (torch threads for training, default: all cores),
# DEMO_TEACHER_TIME / DEMO_STUDENT_TIME / DEMO_NOKD_TIME (DD:HH:MM:SS wall-time caps).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
REPORT=reports/demo
RUNS=$REPORT/runs
THREADS=${DEMO_THREADS:-null}
TEACHER_TIME=${DEMO_TEACHER_TIME:-00:00:07:00}
STUDENT_TIME=${DEMO_STUDENT_TIME:-00:00:07:00}
NOKD_TIME=${DEMO_NOKD_TIME:-00:00:07:00}
mkdir -p "$RUNS"
TIMINGS=$REPORT/timings.md
[ "${DEMO_FRESH:-0}" = 1 ] && rm -rf "$RUNS"/* "$REPORT"/eval "$REPORT"/bench
printf '| stage | seconds |\n|---|---|\n' > "$TIMINGS.tmp"
START=$(date +%s)

stage() {  # stage <name> <command...>: run and record its wall time
    local name=$1; shift
    local t0; t0=$(date +%s)
    echo "==> [$name] $*"
    "$@"
    local dt=$(( $(date +%s) - t0 ))
    echo "| $name | $dt |" >> "$TIMINGS.tmp"
    echo "<== [$name] ${dt}s"
}

train_run() {  # train_run <run name> <overrides...>: train unless DONE; resume an interrupted run
    local name=$1; shift
    local dir=$RUNS/$name
    if [ -f "$dir/DONE" ]; then
        echo "==> [$name] done before ($dir), skipped"
        return
    fi
    local resume=()
    [ -f "$dir/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
    stage "$name" "$PY" train.py "$@" "threads=$THREADS" "hydra.run.dir=$dir" "${resume[@]}"
    if [ -f "$dir/COLLAPSED" ]; then  # written by the CollapseDetector callback
        echo "error: [$name] $(cat "$dir/COLLAPSED")" >&2
        exit 3
    fi
    touch "$dir/DONE"
}

ckpt_of() {  # the checkpoint evaluated: best validation PSNR, else the last one
    if [ -f "$RUNS/$1/checkpoints/best.ckpt" ]; then echo "$RUNS/$1/checkpoints/best.ckpt"
    else echo "$RUNS/$1/checkpoints/last.ckpt"; fi
}

# 1. data (denoiser-render keeps frames that exist, so a second run costs seconds)
stage render "$BIN/denoiser-render" dataset=demo

# 2-4. networks
train_run teacher experiment=demo_teacher "trainer.max_time=$TEACHER_TIME"
train_run student_distilled experiment=demo_distill "model.teacher_ckpt=$(ckpt_of teacher)" \
    "trainer.max_time=$STUDENT_TIME"
# the comparison without distillation gets the same number of optimizer steps as the distilled
# student reached (its steps are cheaper: no teacher, no critic), capped by DEMO_NOKD_TIME
STEPS=$("$PY" -c "import sys, torch; print(torch.load(sys.argv[1], map_location='cpu', weights_only=True)['global_step'])" \
    "$RUNS/student_distilled/checkpoints/last.ckpt")
train_run student_no_kd experiment=demo_distill ablation=no_kd "trainer.max_steps=$STEPS" "trainer.max_time=$NOKD_TIME"

# 5. evaluation on the held-out test split, then the accuracy-vs-time benchmark
CKPTS="{teacher: $(ckpt_of teacher), student_distilled: $(ckpt_of student_distilled), student_no_kd: $(ckpt_of student_no_kd)}"
stage eval "$BIN/denoiser-eval" data=demo "ckpt=$CKPTS" "out_dir=$REPORT/eval"
# CPU budget: eager PyTorch and ONNX Runtime at 256x256 and 1080p (the teacher at 256x256 only)
stage bench "$BIN/denoiser-bench" data=demo "ckpt=$CKPTS" "eval_csv=$REPORT/eval/metrics.csv" \
    "out_dir=$REPORT/bench" "sizes=[[256,256],[1080,1920]]" "use_backends=[eager,onnxruntime]" \
    "skip={teacher: [[1080,1920]]}" repeats=3

# 6. the report directory
cp "$REPORT/eval/metrics.md" "$REPORT/metrics.md"
cp "$REPORT/bench/report.md" "$REPORT/bench.md"
rm -rf "$REPORT/crops" && cp -r "$REPORT/eval/images" "$REPORT/crops"
for plot in "$REPORT"/bench/*.png; do [ -f "$plot" ] && cp "$plot" "$REPORT/"; done
echo "| total | $(( $(date +%s) - START )) |" >> "$TIMINGS.tmp"
mv "$TIMINGS.tmp" "$TIMINGS"

cat <<EOF

==== demo finished: $REPORT/ ====
  metrics table      $REPORT/metrics.md   (per sequence: $REPORT/eval/metrics.csv)
  accuracy vs time   $REPORT/accuracy_vs_time.png   (table: $REPORT/bench.md)
  crops (PNG)        $REPORT/crops/
  TensorBoard        tensorboard --logdir $RUNS
  checkpoints        $RUNS/{teacher,student_distilled,student_no_kd}/checkpoints/
  stage timings      $TIMINGS
EOF
cat "$REPORT/metrics.md"
cat "$REPORT/bench.md"
cat "$TIMINGS"
