#!/usr/bin/env bash
# `make fast-motion`: issue 33's val study of recipes that train on the fast-motion families, after
# make demo (docs/results_log.md, "Fast object motion"). Everything is chosen on val; no test split
# is read.
#
#   1. render data/fast (denoiser-render dataset=fast: fast_objects for train and unlabeled,
#      fast_spin for val; sequences that exist are kept)
#   2. teacher candidates: experiment=demo_teacher with data.extra_roots=[data/fast] and each
#      candidate's overrides, one run per seed, FAST_JOBS side by side
#      -> reports/fast/teachers/runs/<candidate>_s<seed> (a collapse is kept and listed)
#   3. denoiser-eval of every teacher, and of make demo's teacher (the row demo_teacher), on the
#      Mitsuba val (data/demo's val plus data/fast's) and on the Blender Cycles val when
#      data/blender/val exists (make blender-val)
#   4. the table: python -m denoiser.commands.val_table -> reports/fast/teachers/val_table.md
#      (PSNR frames 2+, paired intervals over val sequences against the first candidate and OIDN-fast)
#   5. with FAST_STUDENT_TEACHER=<candidate> (or demo: make demo's teacher): student candidates
#      (FAST_STUDENTS) distilled from that candidate's first-seed teacher on the same data
#      (experiment=demo_distill), the same seeds, evaluated with make demo's distilled students
#      ("base": today's recipe) -> reports/fast/students/val_table.md
#
# Knobs (environment):
#   FAST_TEACHERS         teacher candidates, "name:override,override;name:..." (an override's value
#                         may hold a list or a map, whose commas do not split:
#                         data.augment.noise_scale=[0.2,1.0]); default the demo's lr, a lower lr and
#                         a longer warm-up; none: no teacher step
#   FAST_SEEDS            default "0 1 2"
#   FAST_TEACHER_SEEDS    the teachers' seeds (default FAST_SEEDS); the students learn from the first
#   FAST_JOBS             runs side by side (default 2)
#   FAST_THREADS          torch threads per run (default 1); FAST_TEACHER_THREADS for the teachers
#   FAST_ROOTS            the dataset presets rendered and joined through data.extra_roots
#                         (default "fast"; e.g. "fast fast_more")
#   FAST_REPORT           default reports/fast
#   FAST_STUDENT_TEACHER  default empty: no step 5
#   FAST_STUDENTS         student candidates, the same form; default "fast:" (the recipe on the new
#                         data) and "disagree:ablation=history_disagreement" (the history disagreement
#                         input, denoiser.nn.temporal)
#   FAST_ALSO_STUDENTS    finished candidates of another run of this script, evaluated and tabled
#                         beside these (paired): "name:<its students/runs dir>;..." (default none)
# Resumable as the other pipelines: denoiser-train skips a finished run (skip_done=true) and
# resumes an interrupted one (ckpt_path=auto; scripts/lib.sh); an evaluation is redone only when
# its checkpoints changed.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PY="$VENV/bin/python"
BIN="$VENV/bin"
DATA=${DENOISER_DATA:-data}
DEMO=reports/demo/runs
REPORT=${FAST_REPORT:-reports/fast}
ROOTS=${FAST_ROOTS:-fast}
SEEDS=${FAST_SEEDS:-0 1 2}
TSEEDS=${FAST_TEACHER_SEEDS:-$SEEDS}
JOBS=${FAST_JOBS:-2}
THREADS=${FAST_THREADS:-1}
TTHREADS=${FAST_TEACHER_THREADS:-$THREADS}
TEACHERS=${FAST_TEACHERS:-"lr2e3:model.optimizer.lr=2e-3;lr1e3:model.optimizer.lr=1e-3;warmup200:model.scheduler.warmup_steps=200"}
STUDENT_TEACHER=${FAST_STUDENT_TEACHER:-}
STUDENTS=${FAST_STUDENTS:-"fast:;disagree:ablation=history_disagreement"}
ROOT_DIRS=()
for root in $ROOTS; do ROOT_DIRS+=("$DATA/$root"); done
EXTRA="data.extra_roots=[$(IFS=,; echo "${ROOT_DIRS[*]}")]"
# shellcheck source=scripts/lib.sh
. scripts/lib.sh

[ -f "$DEMO/teacher/DONE" ] || { echo "error: $DEMO/teacher: no finished demo teacher (run make demo first)" >&2; exit 2; }
candidates() {  # candidates <knob> <value> <names array> <overrides map>: parse "name:o,o;name:..."
    local knob=$1 spec name
    local -n names=$3 overrides=$4
    local -a specs=()
    [ "$2" = none ] || IFS=';' read -ra specs <<< "$2"
    for spec in "${specs[@]}"; do
        name=${spec%%:*}
        [[ "$spec" == *:* && "$name" =~ ^[A-Za-z][A-Za-z0-9]*$ && "$name" != base ]] || {
            echo "error: $knob: '$spec' is not name:override,... (name: a letter, then letters and digits; not base)" >&2
            exit 2
        }
        overrides[$name]=${spec#*:}
        names+=("$name")
    done
}
split_overrides() {  # split_overrides <"o,o,..."> <array name>: split at the commas outside [] and {}
    local s=$1 cur="" ch depth=0 i
    local -n parts=$2
    parts=()
    for ((i = 0; i < ${#s}; i++)); do
        ch=${s:i:1}
        case $ch in '[' | '{') depth=$((depth + 1)) ;; ']' | '}') depth=$((depth - 1)) ;; esac
        if [ "$ch" = , ] && [ "$depth" -eq 0 ]; then parts+=("$cur"); cur=""; else cur+=$ch; fi
    done
    [ -z "$cur" ] || parts+=("$cur")
}
declare -A OVERRIDES=() SOVERRIDES=() ALSO=()
NAMES=()
SNAMES=()
candidates FAST_TEACHERS "$TEACHERS" NAMES OVERRIDES
candidates FAST_STUDENTS "$STUDENTS" SNAMES SOVERRIDES
ANAMES=()
candidates FAST_ALSO_STUDENTS "${FAST_ALSO_STUDENTS:-none}" ANAMES ALSO
for name in "${ANAMES[@]}"; do
    [ -z "${SOVERRIDES[$name]+x}" ] || { echo "error: FAST_ALSO_STUDENTS: '$name' is also a candidate of FAST_STUDENTS" >&2; exit 2; }
    for seed in $SEEDS; do
        [ -f "${ALSO[$name]}/${name}_s$seed/DONE" ] \
            || { echo "error: FAST_ALSO_STUDENTS: ${ALSO[$name]}/${name}_s$seed: no finished run" >&2; exit 2; }
    done
done
SEEDS_LIST="[${SEEDS// /,}]"
TSEEDS_LIST="[${TSEEDS// /,}]"
if [ -n "$STUDENT_TEACHER" ] && [ "$STUDENT_TEACHER" != demo ] && [ -z "${OVERRIDES[$STUDENT_TEACHER]+x}" ]; then
    echo "error: FAST_STUDENT_TEACHER: '$STUDENT_TEACHER' is not demo or a candidate of FAST_TEACHERS (${NAMES[*]})" >&2
    exit 2
fi

for root in $ROOTS; do
    echo "==> [render] $DATA/$root"
    "$BIN/denoiser-render" "dataset=$root"
done

evaluate() {  # evaluate <out dir> <ckpt map>: the Mitsuba val and, when rendered, the Blender val
    local out=$1 ckpts=$2
    if fresh "$out/mitsuba_val" "$ckpts"; then
        echo "==> [eval] $out/mitsuba_val: the same checkpoints, done before"
    else
        echo "==> [eval] $out/mitsuba_val"
        "$BIN/denoiser-eval" data=demo split=val "$EXTRA" "ckpt={$ckpts}" "out_dir=$out/mitsuba_val" \
            '~baselines.oidn_balanced' '~baselines.oidn_high'
        echo "$ckpts" > "$out/mitsuba_val/inputs.txt"
    fi
    if [ ! -d "$DATA/blender/val" ]; then
        echo "warning: $DATA/blender/val: no Blender val sequences (make blender-val), the Mitsuba val only" >&2
    elif fresh "$out/blender_val" "$ckpts"; then
        echo "==> [eval] $out/blender_val: the same checkpoints, done before"
    else
        echo "==> [eval] $out/blender_val"
        "$BIN/denoiser-eval" layout=blender "data.root=$DATA/blender" split=val "ckpt={$ckpts}" \
            "out_dir=$out/blender_val" '~baselines.oidn_balanced' '~baselines.oidn_high'
        echo "$ckpts" > "$out/blender_val/inputs.txt"
    fi
}
table() {  # table <out dir> <reference> <candidates> <baselines> <title> <seeds>: val_table over what was evaluated
    local out=$1 vals evals
    vals=$(printf ' + %s/val' "${ROOT_DIRS[@]}")
    evals="{mitsuba: {title: 'Mitsuba val ($DATA/demo/val$vals)', csv: $1/mitsuba_val/metrics.csv}"
    [ -f "$out/blender_val/metrics.csv" ] && evals="$evals, blender: {title: 'Blender Cycles val ($DATA/blender/val)', csv: $out/blender_val/metrics.csv}"
    "$PY" -m denoiser.commands.val_table "out=$out/val_table.md" "evals=$evals}" "reference=$2" \
        "candidates=$3" "plain_rows=$4" "seeds=$6" "labels=$5"
}
train() {  # train <run dir> <overrides...>: one run, its output in <run dir>.log; a collapse is listed
    local dir=$1; shift
    echo "==> [$dir]"
    mkdir -p "$(dirname "$dir")"
    OMP_NUM_THREADS=$THREADS train_run "$dir" "$@" "$EXTRA" "threads=$THREADS" trainer.enable_progress_bar=false \
        callbacks.progress=null > "$dir.log" 2>&1 || { echo "error: [$dir] failed, see $dir.log" >&2; return 1; }
    [ -f "$dir/COLLAPSED" ] && echo "warning: [$dir] $(cat "$dir/COLLAPSED") (kept, listed in collapsed.txt)" >&2
    echo "<== [$dir]"
}

# -- teachers (FAST_TEACHERS=none: none)
TRUNS=$REPORT/teachers/runs
if [ "${#NAMES[@]}" -gt 0 ]; then
    teacher_run() {  # teacher_run <name>_s<seed>
        local name=${1%_s*} seed=${1##*_s}
        local -a extra
        split_overrides "${OVERRIDES[$name]}" extra
        THREADS=$TTHREADS train "$TRUNS/$1" experiment=demo_teacher "seed=$seed" "${extra[@]}"
    }
    RUNS_LIST=()
    for name in "${NAMES[@]}"; do for seed in $TSEEDS; do RUNS_LIST+=("${name}_s$seed"); done; done
    run_jobs "$JOBS" teacher_run "${RUNS_LIST[@]}" || exit 3
    CKPTS="demo_teacher: $(best "$DEMO/teacher")"
    LABELS="{"
    for name in "${NAMES[@]}"; do
        for seed in $TSEEDS; do CKPTS="$CKPTS, ${name}_s$seed: $(best "$TRUNS/${name}_s$seed")"; done
        LABELS="$LABELS$name: 'experiment=demo_teacher $EXTRA ${OVERRIDES[$name]}', "
    done
    LABELS="${LABELS%, }}"
    evaluate "$REPORT/teachers" "$CKPTS"
    find "$TRUNS" -name COLLAPSED -printf '%h: ' -exec cat {} \; > "$REPORT/teachers/collapsed.txt" 2>/dev/null || true
    CANDIDATES=$(IFS=,; echo "[${NAMES[*]}]")
    table "$REPORT/teachers" "${NAMES[0]}" "$CANDIDATES" "['noisy input',OIDN-fast,demo_teacher]" "$LABELS" "$TSEEDS_LIST"
fi

# -- student candidates, taught by the chosen teacher
if [ -n "$STUDENT_TEACHER" ]; then
    FIRST=${TSEEDS%% *}
    if [ "$STUDENT_TEACHER" = demo ]; then TEACHER=$(best "$DEMO/teacher"); else TEACHER=$(best "$TRUNS/${STUDENT_TEACHER}_s$FIRST"); fi
    SRUNS=$REPORT/students/runs
    student_run() {  # student_run <name>_s<seed>
        local name=${1%_s*}
        local -a extra=()
        split_overrides "${SOVERRIDES[$name]}" extra
        train "$SRUNS/$1" experiment=demo_distill "model.teacher_ckpt=$TEACHER" "seed=${1##*_s}" "${extra[@]}"
    }
    RUNS_LIST=()
    for name in "${SNAMES[@]}"; do for seed in $SEEDS; do RUNS_LIST+=("${name}_s$seed"); done; done
    run_jobs "$JOBS" student_run "${RUNS_LIST[@]}" || exit 3
    CKPTS=""
    LABELS="{base: \"make demo's distilled students (today's recipe, data/demo)\""
    for seed in $SEEDS; do
        [ -f "$DEMO/student_distilled_s$seed/DONE" ] \
            || { echo "error: $DEMO/student_distilled_s$seed: no finished demo student (make demo DEMO_SEEDS)" >&2; exit 2; }
        CKPTS="$CKPTS${CKPTS:+, }base_s$seed: $(best "$DEMO/student_distilled_s$seed")"
    done
    for name in "${SNAMES[@]}"; do
        for seed in $SEEDS; do CKPTS="$CKPTS, ${name}_s$seed: $(best "$SRUNS/${name}_s$seed")"; done
        LABELS="$LABELS, $name: 'experiment=demo_distill $EXTRA ${SOVERRIDES[$name]}, taught by $TEACHER'"
    done
    for name in "${ANAMES[@]}"; do
        for seed in $SEEDS; do CKPTS="$CKPTS, ${name}_s$seed: $(best "${ALSO[$name]}/${name}_s$seed")"; done
        LABELS="$LABELS, $name: 'the runs ${ALSO[$name]}/${name}_s* (their recipe: the val_table.md beside that folder)'"
    done
    evaluate "$REPORT/students" "$CKPTS"
    ALL=("${SNAMES[@]}" "${ANAMES[@]}")
    table "$REPORT/students" base "[base,$(IFS=,; echo "${ALL[*]}")]" "['noisy input',OIDN-fast]" "$LABELS}" "$SEEDS_LIST"
fi
echo "==== fast-motion finished: $(ls "$REPORT"/{teachers,students}/val_table.md 2>/dev/null | tr '\n' ' ')===="
