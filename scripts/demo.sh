#!/usr/bin/env bash
# `make demo`: the whole pipeline on the small simulated demo dataset, on the CPU. Its recipe is
# refine (DEMO_RECIPE, below): the paper's recipe trained first into reports/demo/runs, then its
# teacher and students fine-tuned on fast-moving objects into reports/demo_refine, each student
# evaluated as its weights interpolated with its start; DEMO_RECIPE=demo stops at the paper's.
#
#   1. render data/demo (denoiser-render dataset=demo; frames that exist are kept: cached)
#      (and the families a recipe adds: DEMO_RECIPE=tune or motion, data/fast, fast_more, vivid)
#   2. train the demo teacher (experiment=demo_teacher, seed 0; DEMO_RECIPE=tune then fine-tunes it on
#      the fast-motion recipe: experiment=demo_motion_tune model.init_ckpt=<teacher>, runs/teacher_tuned)
#   3. distill the demo student, once per seed of DEMO_SEEDS (experiment=demo_distill seed=k,
#      teacher from step 2)
#   4. train the same student without KD, on references alone (experiment=demo seed=k), same
#      seeds and the same number of steps (refine, the default: steps 2-4 are the paper recipe's runs in
#      reports/demo/runs, then the teacher's fine-tune and each student fine-tuned from its namesake
#      there, reports/demo_refine/runs/teacher_tuned and runs/student_*, then interpolated with it)
#   5. evaluate noisy input, OIDN, teacher and every student on the held-out test sequences
#      (denoiser-eval) and time them (denoiser-bench); the same networks on the Blender Cycles
#      sequences when they exist (DEMO_BLENDER, default data/blender: `make blender` renders
#      them; bpy is an optional extra) into <report>/blender/
#   6. write <report> (reports/demo_refine; DEMO_RECIPE=demo: reports/demo): summary.md (run id, commit, seeds, steps, test-split hash, results
#      with mean +- std over seeds), metrics table, accuracy-vs-time plot, PNG crops, TensorBoard logs
#
# Budgets are steps (the experiment configs' trainer.max_steps) and seeds; max_time in the
# configs is only a safety cap, so the results do not depend on the machine's load.
# Every stage is skipped when its result exists (denoiser-train skips a finished run of the same
# config, skip_done=true, and resumes an interrupted one from its last.ckpt, ckpt_path=auto;
# scripts/lib.sh). DEMO_FRESH=1 retrains everything.
# Knobs (environment): DEMO_SEEDS (default "0 1 2"), DEMO_JOBS (student runs trained at once,
# each with cores/DEMO_JOBS torch threads; default 2), DEMO_THREADS (torch threads of the
# teacher, default: all cores), DEMO_BLENDER (Blender sequences to evaluate on when
# <dir>/test exists; default data/blender, empty: off), DEMO_RECIPE (refine, the default: the paper's
# recipe, then its teacher and students both fine-tuned on issue 33's fast-moving families; demo: the
# paper's recipe alone; tune or motion: the demo teacher fine-tuned on those families, or a teacher
# trained on them from scratch, and students distilled from it; scripts/lib.sh), DEMO_REPORT (default
# reports/demo_refine, reports/demo, reports/demo_tune or reports/demo_motion), DEMO_BASE_RUNS
# (refine: the runs it fine-tunes, default reports/demo/runs), DEMO_REFINE_ALPHA (refine: the
# students evaluated are (1 - alpha) * the paper recipe's + alpha * their fine-tune, weight-space
# interpolation; default 0.75, chosen on val; 1: the fine-tunes as they are).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
# make demo's recipe is refine (issue 33: it keeps the student's gain where objects move fast); the
# other scripts' default, lib.sh's, stays demo, the paper's recipe, whose runs refine starts from
DEMO_RECIPE=${DEMO_RECIPE:-refine}
# shellcheck source=scripts/lib.sh
. scripts/lib.sh   # DEMO_RECIPE: the experiments and datasets
REPORT=${DEMO_REPORT:-reports/$DEMO_RECIPE_NAME}
RUNS=$REPORT/runs
THREADS=${DEMO_THREADS:-null}
SEEDS=${DEMO_SEEDS:-0 1 2}
JOBS=${DEMO_JOBS:-2}
BLENDER=${DEMO_BLENDER-data/blender}
CORES=$(nproc)
JOB_THREADS=$(( CORES / JOBS > 0 ? CORES / JOBS : 1 ))
ALPHA=${DEMO_REFINE_ALPHA:-1}
if [ "$ALPHA" != 1 ] && { [ -z "$DEMO_REFINE_EXPERIMENT" ] || ! [[ $ALPHA =~ ^0?\.[0-9]+$|^0$ ]]; }; then
    echo "error: DEMO_REFINE_ALPHA=$ALPHA: a number in [0, 1], with DEMO_RECIPE=refine (it interpolates refine's students)" >&2
    exit 2
fi
mkdir -p "$RUNS"
TIMINGS=$REPORT/timings.md
[ "${DEMO_FRESH:-0}" = 1 ] && rm -rf "$RUNS"/* "$REPORT"/eval "$REPORT"/bench
timings_begin

# DEMO_RECIPE=refine fine-tunes the default recipe's runs: its teacher and first students are make
# demo's own (DEMO_BASE_RUNS), the fine-tuned ones go to $RUNS
BASE_RUNS=$RUNS
[ -z "$DEMO_REFINE_EXPERIMENT" ] || BASE_RUNS=${DEMO_BASE_RUNS:-reports/demo/runs}
mkdir -p "$BASE_RUNS"

demo_train() {  # demo_train <run dir> <overrides...>: train (skipped when finished, resumed when interrupted)
    local dir=$1; shift
    train_run "$dir" "$@"
    if [ -f "$dir/COLLAPSED" ]; then  # written by the CollapseDetector callback
        echo "error: [${dir##*/}] $(cat "$dir/COLLAPSED")" >&2
        exit 3
    fi
}

# 1. data (denoiser-render keeps frames that exist, so a second run costs seconds)
stage --reuse "${DENOISER_DATA:-data}/demo" '*.exr' render "$BIN/denoiser-render" dataset=demo
# DEMO_RECIPE=tune or motion: the fast-moving and saturated families they train on (conf/base/motion_recipe.yaml)
for family in $DEMO_EXTRA_DATASETS; do
    stage --reuse "${DENOISER_DATA:-data}/$family" '*.exr' "render_$family" "$BIN/denoiser-render" "dataset=$family"
done

# 2-4. networks
stage --reuse "$BASE_RUNS/teacher" DONE teacher demo_train "$BASE_RUNS/teacher" "experiment=$DEMO_TEACHER_EXPERIMENT" \
    seed=0 "threads=$THREADS"
TEACHER=$(best "$BASE_RUNS/teacher")
BASE_TEACHER=$TEACHER   # make demo's teacher, before any fine-tune
if [ -n "$DEMO_TUNE_EXPERIMENT" ]; then  # the teacher fine-tuned on the recipe's data teaches the students
    stage --reuse "$RUNS/teacher_tuned" DONE teacher_tuned demo_train "$RUNS/teacher_tuned" "experiment=$DEMO_TUNE_EXPERIMENT" \
        "model.init_ckpt=$TEACHER" seed=0 "threads=$THREADS"
    TEACHER=$(best "$RUNS/teacher_tuned")
fi
STUDENT_TEACHER=$TEACHER   # the students' teacher; refine's first students are make demo's own, taught by its teacher
[ -z "$DEMO_REFINE_EXPERIMENT" ] || STUDENT_TEACHER=$BASE_TEACHER
# students: every (kind, seed) pair, DEMO_JOBS at a time, each with its share of the cores
STUDENTS=()
for seed in $SEEDS; do STUDENTS+=("student_distilled_s$seed" "student_no_kd_s$seed"); done
student_job() {  # student_job <run dir> <overrides...>: one student run, its log beside its directory
    local dir=$1 name=${1##*/} t0=$SECONDS; shift
    echo "==> [$name]"
    demo_train "$dir" "$@" "seed=${name##*_s}" "threads=$JOB_THREADS" trainer.enable_progress_bar=false \
        callbacks.progress=null > "$dir.log" 2>&1 || { echo "error: [$name] failed, see $dir.log" >&2; return 1; }
    echo "<== [$name] $(( SECONDS - t0 ))s"
}
student_run() {  # student_run <run name>: distilled from STUDENT_TEACHER, or on references alone
    if [[ $1 == student_no_kd_* ]]; then
        student_job "$BASE_RUNS/$1" "experiment=$DEMO_NO_KD_EXPERIMENT"
    else
        student_job "$BASE_RUNS/$1" "experiment=$DEMO_DISTILL_EXPERIMENT" "model.teacher_ckpt=$STUDENT_TEACHER"
    fi
}
refine_run() {  # refine_run <run name>: make demo's student of that name fine-tuned (DEMO_RECIPE=refine)
    local init
    init=$(best "$BASE_RUNS/$1")
    if [[ $1 == student_no_kd_* ]]; then
        student_job "$RUNS/$1" "experiment=$DEMO_NO_KD_REFINE_EXPERIMENT" "model.init_ckpt=$init"
    else
        student_job "$RUNS/$1" "experiment=$DEMO_REFINE_EXPERIMENT" "model.init_ckpt=$init" "model.teacher_ckpt=$TEACHER"
    fi
}
# one row for the students, JOBS side by side (their wall time, not the sum of theirs)
stage --reuse "$BASE_RUNS" DONE students run_jobs "$JOBS" student_run "${STUDENTS[@]}" || exit 3
if [ -n "$DEMO_REFINE_EXPERIMENT" ]; then
    stage --reuse "$RUNS" DONE refine run_jobs "$JOBS" refine_run "${STUDENTS[@]}" || exit 3
fi
# refine with DEMO_REFINE_ALPHA below 1: each student evaluated is its fine-tune interpolated with its
# start, (1 - alpha) * make demo's + alpha * the fine-tune (python -m denoiser.commands.interpolate)
INTERPOLATE=""
if [ -n "$DEMO_REFINE_EXPERIMENT" ] && [ "$ALPHA" != 1 ]; then INTERPOLATE=interpolated_a$ALPHA.ckpt; fi
student_ckpt() {  # student_ckpt <run name>: the checkpoint a student is evaluated and timed with
    if [ -n "$INTERPOLATE" ]; then echo "$RUNS/$1/checkpoints/$INTERPOLATE"; else best "$RUNS/$1"; fi
}
interpolate_run() {  # interpolate_run <run name>: its interpolated checkpoint (student_ckpt)
    "$PY" -m denoiser.commands.interpolate "start=$(best "$BASE_RUNS/$1")" "end=$(best "$RUNS/$1")" \
        "alpha=$ALPHA" "out=$(student_ckpt "$1")"
}
if [ -n "$INTERPOLATE" ]; then
    stage interpolate run_jobs 1 interpolate_run "${STUDENTS[@]}" || exit 3
fi

# 5. evaluation on the held-out test split, then the accuracy-vs-time benchmark
CKPTS="teacher: $TEACHER"
for name in "${STUDENTS[@]}"; do CKPTS="$CKPTS, $name: $(student_ckpt "$name")"; done
FIRST=${SEEDS%% *}
stage eval "$BIN/denoiser-eval" data=demo "ckpt={$CKPTS}" "out_dir=$REPORT/eval" \
    "purpose='make demo: the report of recipe $DEMO_RECIPE'"
if [ -n "$BLENDER" ] && [ -d "$BLENDER/test" ]; then  # a real renderer's sequences (make blender)
    stage blender "$BIN/denoiser-eval" layout=blender "data.root=$BLENDER" "ckpt={$CKPTS}" \
        "purpose='make demo: the Cycles test sequences, report of recipe $DEMO_RECIPE'" \
        "out_dir=$REPORT/blender" '~baselines.oidn_balanced'
else
    rm -rf "$REPORT/blender"  # no stale table in the summary
fi
# the benchmark times one seed per student (the seeds are the same network size); the teacher
# at 256x256 only (seconds per 1080p frame on 2 cores)
BENCH_CKPTS="{teacher: $TEACHER, student_distilled_s$FIRST: $(student_ckpt "student_distilled_s$FIRST"), student_no_kd_s$FIRST: $(student_ckpt "student_no_kd_s$FIRST")}"
stage bench "$BIN/denoiser-bench" data=demo "ckpt=$BENCH_CKPTS" "eval_csv=$REPORT/eval/metrics.csv" \
    "out_dir=$REPORT/bench" "sizes=[[256,256],[1080,1920]]" "use_backends=[eager,onnxruntime,openvino_f32,openvino_bf16]" \
    "skip={teacher: [[1080,1920]]}" repeats=7
SUMMARY_RECIPE=()   # refine: the runs it fine-tunes and the interpolation, named in the summary
[ -z "$DEMO_REFINE_EXPERIMENT" ] || SUMMARY_RECIPE+=("base_runs=$BASE_RUNS")
[ -z "$INTERPOLATE" ] || SUMMARY_RECIPE+=("interpolation_alpha=$ALPHA")
stage summary "$PY" -m denoiser.commands.demo_summary "report=$REPORT" "seeds=[${SEEDS// /,}]" "${SUMMARY_RECIPE[@]}"

# 6. the report directory
cp "$REPORT/eval/metrics.md" "$REPORT/metrics.md"
cp "$REPORT/bench/report.md" "$REPORT/bench.md"
rm -rf "$REPORT/crops" && cp -r "$REPORT/eval/images" "$REPORT/crops"
for plot in "$REPORT"/bench/*.png; do [ -f "$plot" ] && cp "$plot" "$REPORT/"; done
timings_end

cat <<EOF

==== demo finished: $REPORT/ ====
  summary            $REPORT/summary.md   (README table: make readme-results)
  metrics table      $REPORT/metrics.md   (per sequence: $REPORT/eval/metrics.csv)
  accuracy vs time   $REPORT/accuracy_vs_time.png   (table: $REPORT/bench.md)
  crops (PNG)        $REPORT/crops/
  TensorBoard        tensorboard --logdir $RUNS
  checkpoints        $RUNS/{teacher,student_distilled_s*,student_no_kd_s*}/checkpoints/
  stage timings      $TIMINGS
EOF
cat "$REPORT/summary.md"
cat "$TIMINGS"
