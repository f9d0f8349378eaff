#!/usr/bin/env bash
# `make pareto`: the accuracy-vs-time Pareto front of the demo student on the CPU (docs/pareto.md).
#
#   1. render data/demo (denoiser-render dataset=demo; existing frames are kept)
#   2. the demo teacher: reports/demo/runs/teacher when make demo trained it, else trained here
#      exactly as scripts/demo.sh does (experiment=demo_teacher)
#   3. the sweep: denoiser-train -m experiment=pareto over PARETO_AXES (default 2 widths x
#      2 kernel/level settings x temporal on/off = 8 variants), each distilled for PARETO_STEPS
#      steps with seed 0, PARETO_JOBS jobs side by side (joblib launcher), into reports/pareto/runs
#   4. denoiser-eval of the finished variants on the demo's test split (PARETO_EVAL=0: skipped),
#      redone when a checkpoint is newer than its table
#   5. denoiser-pareto: every variant timed one after another on PARETO_BACKEND, then the table,
#      the front, the plot and the front's overrides in reports/pareto/
#
# Resumable: a finished job leaves DONE in its directory and is skipped (skip_done=true), an
# interrupted one resumes from its last.ckpt (ckpt_path=auto); timings are cached per checkpoint.
# Keep PARETO_AXES the same between reruns: job directories are numbered in sweep order
# (a directory holding another variant's finished run is an error, not silently reused).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
REPORT=${PARETO_REPORT:-reports/pareto}
SWEEP=$REPORT/runs
TEACHER=${PARETO_TEACHER_DIR:-reports/demo/runs/teacher}
TEACHER_TIME=${DEMO_TEACHER_TIME:-00:00:07:00}
STEPS=${PARETO_STEPS:-150}
JOBS=${PARETO_JOBS:-2}
THREADS=${PARETO_THREADS:-1}          # torch threads per training job (JOBS x THREADS <= cores)
BACKEND=${PARETO_BACKEND:-openvino}   # a key of denoiser-pareto's backends: openvino | onnxruntime | eager
AXES=${PARETO_AXES:-"net=demo_student_w05,demo_student kernel.sizes=[3,5,5],[5,5,5] ablation=none,no_temporal"}
OIDN_CSV=${PARETO_OIDN_CSV:-reports/demo/bench/bench.csv}   # make demo's benchmark: its OIDN rows join the table
EVAL=${PARETO_EVAL:-1}                # 1: denoiser-eval of the variants on the test split (test PSNR column)

echo "==> [render] data/demo"
"$BIN/denoiser-render" dataset=demo

if [ -f "$TEACHER/DONE" ]; then
    echo "==> [teacher] $TEACHER done before, reused"
else
    resume=()
    [ -f "$TEACHER/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
    echo "==> [teacher] training $TEACHER (experiment=demo_teacher)"
    "$PY" train.py experiment=demo_teacher "trainer.max_time=$TEACHER_TIME" "hydra.run.dir=$TEACHER" "${resume[@]}"
    touch "$TEACHER/DONE"
fi
if [ -f "$TEACHER/checkpoints/best.ckpt" ]; then TEACHER_CKPT=$TEACHER/checkpoints/best.ckpt
else TEACHER_CKPT=$TEACHER/checkpoints/last.ckpt; fi

echo "==> [sweep] $SWEEP: $AXES, $STEPS steps each"
# shellcheck disable=SC2086 # AXES is a list of overrides
"$PY" train.py -m experiment=pareto $AXES "model.teacher_ckpt=$TEACHER_CKPT" "trainer.max_steps=$STEPS" \
    "threads=$THREADS" skip_done=true ckpt_path=auto trainer.enable_progress_bar=false callbacks.progress=null \
    hydra/launcher=joblib "hydra.launcher.n_jobs=$JOBS" "hydra.sweep.dir=$SWEEP" 'hydra.sweep.subdir=${hydra.job.num}'

extra=()
[ -f "$OIDN_CSV" ] && extra+=("oidn_csv=$OIDN_CSV")
if [ "$EVAL" = 1 ]; then  # test PSNR of every finished job (and of OIDN) on the demo's test split
    EVAL_CSV=$REPORT/eval/metrics.csv
    ckpts=""
    for dir in "$SWEEP"/*/; do
        [ -f "$dir/DONE" ] && [ -f "$dir/checkpoints/last.ckpt" ] && ckpts+="job$(basename "$dir"): ${dir}checkpoints/last.ckpt, "
    done
    if [ -n "$ckpts" ] && { [ ! -f "$EVAL_CSV" ] || [ -n "$(find "$SWEEP" -name last.ckpt -newer "$EVAL_CSV")" ]; }; then
        echo "==> [eval] test split: $REPORT/eval"
        "$BIN/denoiser-eval" data=demo "ckpt={${ckpts%, }}" "out_dir=$REPORT/eval"
    fi
    [ -f "$EVAL_CSV" ] && extra+=("eval_csv=$EVAL_CSV")
fi

echo "==> [report] $REPORT (timing on $BACKEND, one network at a time)"
"$BIN/denoiser-pareto" "sweep_dir=$SWEEP" "out_dir=$REPORT" "backend=$BACKEND" "${extra[@]}"

cat <<END

==== pareto finished: $REPORT/ ====
  table              $REPORT/pareto.md   ($REPORT/pareto.csv)
  accuracy vs time   $REPORT/accuracy_vs_time.png
  the front          $REPORT/front.txt   (each line: the overrides of a denoiser-train command)
  TensorBoard        tensorboard --logdir $SWEEP   (HPARAMS: final/psnr per variant)
END
