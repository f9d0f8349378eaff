#!/usr/bin/env bash
# `make pareto`: the accuracy-vs-time Pareto front of the demo student on the CPU (docs/pareto.md).
#
#   1. render data/demo (denoiser-render dataset=demo; existing frames are kept)
#   2. the demo teacher: reports/demo/runs/teacher when make demo trained it, else trained here
#      as scripts/demo.sh does (experiment=demo_teacher) but for PARETO_TEACHER_STEPS steps
#      (default 300 of its 1200, so that make pareto alone fits its hour; run make demo first
#      for the full teacher)
#   3. the sweep: denoiser-train -m experiment=pareto over PARETO_AXES (default 2 widths x
#      2 kernel/level settings x temporal on/off = 8 variants), each distilled for PARETO_STEPS
#      steps with seed 0, PARETO_JOBS jobs side by side (joblib launcher), into reports/pareto/runs
#   4. denoiser-eval of OIDN (fast, high) on the demo's val split: the baselines' val PSNR
#   5. denoiser-pareto: every variant timed one after another on PARETO_BACKEND, OIDN on the
#      same frames and threads, then the table, the front, the plot and the front's overrides
#   6. the front's variants retrained with the seeds of PARETO_FRONT_SEEDS (default "1 2"; with
#      seed 0, 3 seeds) into reports/pareto/seeds/<job>_s<seed>, then denoiser-pareto again over
#      both directories: a variant's val PSNR is its mean ± std over seeds, and the front is
#      recomputed from those means
#   7. denoiser-eval of every finished run on the demo's test split (PARETO_EVAL=0: skipped),
#      redone when a checkpoint is newer than its table: the test columns (reported, never chosen on)
#
# Resumable: a finished job leaves DONE in its directory and is skipped (skip_done=true), an
# interrupted one resumes from its last.ckpt (ckpt_path=auto); timings are cached per checkpoint.
# Stage times: $REPORT/timings.md (a reused run keeps the seconds of the run that did it).
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
TEACHER_STEPS=${PARETO_TEACHER_STEPS:-300}
STEPS=${PARETO_STEPS:-150}
JOBS=${PARETO_JOBS:-2}
THREADS=${PARETO_THREADS:-1}          # torch threads per training job (JOBS x THREADS <= cores)
BACKEND=${PARETO_BACKEND:-openvino}   # denoiser-pareto's backend=: a name of conf/backends/ (openvino = openvino_f32, onnxruntime, eager, ...)
AXES=${PARETO_AXES:-"net=demo_student_w05,demo_student kernel.sizes=[3,5,5],[5,5,5] ablation=none,no_temporal"}
EVAL=${PARETO_EVAL:-1}                # 1: denoiser-eval of the variants on the test split (test PSNR column)
FRONT_SEEDS=${PARETO_FRONT_SEEDS:-"1 2"}   # more seeds for the front's variants ("" : none)
SEEDS_DIR=$REPORT/seeds
TIMINGS=$REPORT/timings.md
# shellcheck source=scripts/lib.sh
. scripts/lib.sh
mkdir -p "$REPORT"
timings_begin

stage --reuse "${DENOISER_DATA:-data}/demo" '*.exr' render "$BIN/denoiser-render" dataset=demo

if [ -f "$TEACHER/DONE" ]; then   # make demo's teacher (or an earlier one), whatever its steps
    echo "==> [teacher] $TEACHER done before, reused"
else
    echo "==> [teacher] training $TEACHER (experiment=demo_teacher, $TEACHER_STEPS steps)"
    stage --reuse "$TEACHER" DONE teacher train_run "$TEACHER" experiment=demo_teacher "trainer.max_steps=$TEACHER_STEPS"
fi
TEACHER_CKPT=$(best "$TEACHER")

echo "==> [sweep] $SWEEP: $AXES, $STEPS steps each"
# shellcheck disable=SC2086 # AXES is a list of overrides
stage --reuse "$SWEEP" DONE sweep "$PY" train.py -m experiment=pareto $AXES "model.teacher_ckpt=$TEACHER_CKPT" "trainer.max_steps=$STEPS" \
    "threads=$THREADS" skip_done=true ckpt_path=auto trainer.enable_progress_bar=false callbacks.progress=null \
    hydra/launcher=joblib "hydra.launcher.n_jobs=$JOBS" "hydra.sweep.dir=$SWEEP" 'hydra.sweep.subdir=${hydra.job.num}'

# OIDN's val PSNR (the front is chosen on val; OIDN is timed by denoiser-pareto on the same frames)
VAL_CSV=$REPORT/eval_val/metrics.csv
if [ ! -f "$VAL_CSV" ]; then
    stage eval_val "$BIN/denoiser-eval" data=demo split=val '~baselines.oidn_balanced' "out_dir=$REPORT/eval_val"
fi
report() {  # report <stage name> <sweep dir...>: denoiser-pareto over them (timings cached per checkpoint)
    local name=$1 dirs extra=()
    shift
    dirs=$(IFS=,; echo "$*")
    [ -f "$REPORT/eval/metrics.csv" ] && extra+=("eval_csv=$REPORT/eval/metrics.csv")
    echo "    (timing on $BACKEND, one network at a time; OIDN on the same frames)"
    stage "$name" "$BIN/denoiser-pareto" "sweep_dir=[$dirs]" "out_dir=$REPORT" "backend=$BACKEND" baselines=default \
        baselines.noisy=null baselines.oidn_balanced=null "baseline_eval_csv=$VAL_CSV" "${extra[@]}"
}
report report "$SWEEP"

if [ -n "$FRONT_SEEDS" ]; then  # the front's variants with more seeds, before any claim about the front
    seeds=${FRONT_SEEDS// /,}
    while IFS=$'\t' read -r job line; do
        eval "overrides=($line)"
        stage --reuse "$SEEDS_DIR" DONE "front_seeds_$job" "$PY" train.py -m "${overrides[@]}" "seed=$seeds" hydra/launcher=joblib "hydra.launcher.n_jobs=$JOBS" \
            "hydra.sweep.dir=$SEEDS_DIR" "hydra.sweep.subdir=${job}_s\${seed}"
    done < <("$PY" -c 'import csv, shlex, sys
for r in csv.DictReader(open(sys.argv[1])):
    if r["front"] == "True" and r["kind"] == "network" and r["seeds"] in ("cfg", "0"):
        print(r["job"], " ".join(shlex.quote(o) for o in r["overrides"].split()), sep="\t")' "$REPORT/pareto.csv")
fi

if [ "$EVAL" = 1 ]; then  # test PSNR of every finished run on the demo's test split: reported, never chosen on
    EVAL_CSV=$REPORT/eval/metrics.csv
    ckpts=""
    for dir in "$SWEEP"/*/ "$SEEDS_DIR"/*/; do
        [ -f "$dir/DONE" ] && [ -f "$dir/checkpoints/last.ckpt" ] && ckpts+="job$(basename "$dir"): ${dir}checkpoints/last.ckpt, "
    done
    if [ -n "$ckpts" ] && { [ ! -f "$EVAL_CSV" ] || [ -n "$(find "$SWEEP" "$SEEDS_DIR" -name last.ckpt -newer "$EVAL_CSV" 2>/dev/null)" ]; }; then
        stage eval "$BIN/denoiser-eval" data=demo "ckpt={${ckpts%, }}" "out_dir=$REPORT/eval" '~baselines.oidn_balanced' \
            "purpose='make pareto: the test column (reported, never chosen on)'"
    fi
fi
if [ -d "$SEEDS_DIR" ]; then report report_seeds "$SWEEP" "$SEEDS_DIR"; else report report_seeds "$SWEEP"; fi
timings_end

cat <<END

==== pareto finished: $REPORT/ ====
  table              $REPORT/pareto.md   ($REPORT/pareto.csv)
  accuracy vs time   $REPORT/accuracy_vs_time.png
  the front          $REPORT/front.txt   (each line: the overrides of a denoiser-train command)
  TensorBoard        tensorboard --logdir $SWEEP   (HPARAMS: final/psnr per variant)
END
