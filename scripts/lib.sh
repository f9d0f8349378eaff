# What the pipeline scripts (demo.sh, compare.sh, pareto.sh, ablations.sh, paper.sh, fast_motion.sh) share; sourced
# after `set -euo pipefail` and `cd` to the checkout. Training itself is denoiser-train's: it skips
# a finished run (skip_done=true: DONE and metrics.json in the run directory, the same config) and
# resumes an interrupted one from its last.ckpt (ckpt_path=auto); a script only names the run.
# Needs: BIN (the virtual environment's bin directory); TIMINGS (the stage-time table) for
# timings_begin, stage and timings_end.

# make demo's recipe (scripts/demo.sh), said once for the scripts that train beside its runs and reuse
# them (ablations.sh, compare.sh): the teacher, the experiment that fine-tunes it (or none), the
# distilled student, the student on references alone, and the datasets rendered besides data/demo.
# DEMO_TEACHER_RUN names the run that taught the students (teacher, or teacher_tuned after a tune).
#   demo (the default): the demo's families only: demo_teacher, demo_distill and demo;
#   tune: issue 33's recipe for fast-moving objects. The demo's teacher, fine-tuned for 400 steps on
#     conf/base/motion_recipe.yaml (the fast-moving and saturated families, noise-level augmentation;
#     experiment=demo_motion_tune, runs/teacher_tuned), and students distilled from it on the same
#     data (reports/demo_tune). Ahead of OIDN-fast on the Cycles val, 0.41 dB behind the default on
#     the demo's test split;
#   motion: the same with a teacher trained on the motion recipe from scratch (reports/demo_motion),
#     also 0.41 dB behind on the demo's test split;
#   refine: the default recipe's teacher and students (DEMO_BASE_RUNS, default reports/demo/runs:
#     make demo's own, trained there first when missing), the teacher fine-tuned as in tune
#     (runs/teacher_tuned), then each student fine-tuned under it on the same data, 400 steps at lr
#     5e-4 (experiment=demo_motion_distill_tune; the no-KD students on references,
#     demo_motion_nokd_tune), into reports/demo_refine; each evaluated as its weights interpolated with
#     its start, (1 - a) * make demo's + a * the fine-tune, a = DEMO_REFINE_ALPHA (0.75, chosen on val:
#     ahead of OIDN-fast on the Cycles val, tied with make demo's students on the test families' val;
#     the fine-tunes alone, a = 1, fell 0.47 dB there). docs/results_log.md, "Fast object motion", has
#     the figures.
# DEMO_REFINE_EXPERIMENT and DEMO_NO_KD_REFINE_EXPERIMENT are empty but for refine, which also sets
# DEMO_REFINE_ALPHA when unset (scripts/demo.sh refuses it for another recipe).
case "${DEMO_RECIPE:-demo}" in
    demo) DEMO_TEACHER_EXPERIMENT=demo_teacher DEMO_TUNE_EXPERIMENT="" DEMO_DISTILL_EXPERIMENT=demo_distill
          DEMO_NO_KD_EXPERIMENT=demo DEMO_EXTRA_DATASETS="" DEMO_RECIPE_NAME=demo ;;
    tune) DEMO_TEACHER_EXPERIMENT=demo_teacher DEMO_TUNE_EXPERIMENT=demo_motion_tune
          DEMO_DISTILL_EXPERIMENT=demo_motion_distill DEMO_NO_KD_EXPERIMENT=demo_motion
          DEMO_EXTRA_DATASETS="fast fast_more vivid" DEMO_RECIPE_NAME=demo_tune ;;
    motion) DEMO_TEACHER_EXPERIMENT=demo_motion_teacher DEMO_TUNE_EXPERIMENT="" DEMO_DISTILL_EXPERIMENT=demo_motion_distill
            DEMO_NO_KD_EXPERIMENT=demo_motion DEMO_EXTRA_DATASETS="fast fast_more vivid" DEMO_RECIPE_NAME=demo_motion ;;
    refine) DEMO_TEACHER_EXPERIMENT=demo_teacher DEMO_TUNE_EXPERIMENT=demo_motion_tune
            DEMO_DISTILL_EXPERIMENT=demo_distill DEMO_NO_KD_EXPERIMENT=demo
            DEMO_REFINE_EXPERIMENT=demo_motion_distill_tune DEMO_NO_KD_REFINE_EXPERIMENT=demo_motion_nokd_tune
            DEMO_REFINE_ALPHA=${DEMO_REFINE_ALPHA:-0.75}
            DEMO_EXTRA_DATASETS="fast fast_more vivid" DEMO_RECIPE_NAME=demo_refine ;;
    *) echo "error: DEMO_RECIPE=$DEMO_RECIPE: demo, tune, motion or refine" >&2; exit 2 ;;
esac
DEMO_REFINE_EXPERIMENT=${DEMO_REFINE_EXPERIMENT:-} DEMO_NO_KD_REFINE_EXPERIMENT=${DEMO_NO_KD_REFINE_EXPERIMENT:-}
DEMO_TEACHER_RUN=teacher${DEMO_TUNE_EXPERIMENT:+_tuned}

best() {  # best <run dir>: the checkpoint a run is evaluated with: best validation PSNR, else the last
    # (what ckpt=<run dir> loads; a path is printed so that reports name the file)
    if [ -f "$1/checkpoints/best.ckpt" ]; then echo "$1/checkpoints/best.ckpt"; else echo "$1/checkpoints/last.ckpt"; fi
}

train_run() {  # train_run <run dir> <overrides...>: denoiser-train into <run dir>, skipped when finished, resumed
    local dir=$1; shift
    "$BIN/denoiser-train" "$@" skip_done=true ckpt_path=auto "hydra.run.dir=$dir"
}

fresh() {  # fresh <dir> <inputs>: <dir>/inputs.txt holds <inputs> and no checkpoint it names is newer
    # (a step over those checkpoints, e.g. an evaluation, is done; the step writes inputs.txt last)
    [ -f "$1/inputs.txt" ] && [ "$(cat "$1/inputs.txt")" = "$2" ] || return 1
    local f
    for f in $(grep -o '[^ ,{}]*\.ckpt' <<< "$2"); do [ "$f" -nt "$1/inputs.txt" ] && return 1; done
    return 0
}

# The stage-time table: one row per stage, | stage | seconds | run |, the stages one after another
# (jobs side by side are one stage: run_jobs inside stage). A stage whose work an earlier run did
# (finished training runs skipped, frames kept, an evaluation of the same checkpoints) keeps that
# run's seconds and names it in the run column, so that a resumed pipeline's table still says what
# its work costs: the total row is this run's wall time, the work row the sum of every stage's
# seconds (the wall time of a run that reused nothing).

timings_begin() {  # a fresh stage-time table ($TIMINGS.tmp until timings_end); the rows of the last one kept
    declare -gA TIMINGS_BEFORE=()
    local name secs run
    if [ -f "$TIMINGS" ]; then
        while IFS='|' read -r _ name secs run _; do
            read -r name <<< "$name"; read -r secs <<< "$secs"; read -r run <<< "$run"   # trimmed
            [[ "$secs" =~ ^[0-9]+$ ]] && [ "$name" != total ] && [ "$name" != work ] \
                && TIMINGS_BEFORE[$name]="$secs|${run:-an earlier run}"
        done < "$TIMINGS"
    fi
    TIMINGS_RUN="run $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    printf '| stage | seconds | run |\n|---|---:|---|\n' > "$TIMINGS.tmp"
    TIMINGS_START=$(date +%s)
}

timings_row() {  # timings_row <name> <seconds> [reused]: a row of this run, or with "reused" the last
    # table's row of <name> (the run that did the work; this run's seconds when it has none)
    if [ "${3:-}" = reused ] && [ -n "${TIMINGS_BEFORE[$1]:-}" ]; then
        echo "| $1 | ${TIMINGS_BEFORE[$1]%%|*} | ${TIMINGS_BEFORE[$1]#*|} |"
    elif [ "${3:-}" = reused ]; then
        echo "| $1 | $2 | reused (the run that did it is not recorded) |"
    else
        echo "| $1 | $2 | $TIMINGS_RUN |"
    fi >> "$TIMINGS.tmp"
}

none_newer() {  # none_newer <dir> <file name pattern> <marker file>: <dir> holds such files, none newer than <marker>
    [ -d "$1" ] && [ -n "$(find "$1" -name "$2" -print -quit)" ] && [ -z "$(find "$1" -name "$2" -newer "$3" -print -quit)" ]
}

stage() {  # stage [--reuse <dir> <file name pattern>] <name> <command...>: run it between ==>/<== lines
    # and record its wall time; with --reuse, a command that wrote no such file under <dir> (e.g. DONE
    # of a training run it skipped, frames a render kept) reused an earlier run's work (timings_row)
    # (its status is the command's: set -e does not stop a function called before || or &&, so the
    # status is passed on explicitly; a failed step gets no row)
    local reuse=() name t0 dt marker status=0
    if [ "$1" = --reuse ]; then reuse=("$2" "$3"); shift 3; fi
    name=$1; shift
    marker=$(mktemp)
    t0=$(date +%s)
    echo "==> [$name] $*"
    "$@" || status=$?
    dt=$(( $(date +%s) - t0 ))
    if [ "$status" -ne 0 ]; then
        rm -f "$marker"
        echo "<== [$name] failed (exit $status) after ${dt}s"
        return "$status"
    fi
    if [ "${#reuse[@]}" -gt 0 ] && none_newer "${reuse[@]}" "$marker"; then
        timings_row "$name" "$dt" reused
    else
        timings_row "$name" "$dt"
    fi
    rm -f "$marker"
    echo "<== [$name] ${dt}s"
}

timings_end() {  # the total (this run's wall time) and work (every stage's seconds) rows; the table becomes $TIMINGS
    local work
    work=$(awk -F'|' 'NR > 2 { s += $3 } END { print s + 0 }' "$TIMINGS.tmp")
    echo "| total | $(( $(date +%s) - TIMINGS_START )) | $TIMINGS_RUN: wall time |" >> "$TIMINGS.tmp"
    echo "| work | $work | every stage's seconds, reused ones included |" >> "$TIMINGS.tmp"
    mv "$TIMINGS.tmp" "$TIMINGS"
}

run_jobs() {  # run_jobs <jobs> <function> <arg...>: <function> <arg> for every arg, <jobs> side by side;
    # every job runs to its end, then the status is 1 when one failed
    local jobs=$1 fn=$2 running=0 failed=0 arg; shift 2
    for arg in "$@"; do
        "$fn" "$arg" &
        running=$((running + 1))
        if [ "$running" -ge "$jobs" ]; then wait -n || failed=1; running=$((running - 1)); fi
    done
    while [ "$running" -gt 0 ]; do wait -n || failed=1; running=$((running - 1)); done
    return "$failed"
}
