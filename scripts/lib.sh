# What the pipeline scripts (demo.sh, compare.sh, pareto.sh, ablations.sh, paper.sh, fast_motion.sh) share; sourced
# after `set -euo pipefail` and `cd` to the checkout. Training itself is denoiser-train's: it skips
# a finished run (skip_done=true: DONE and metrics.json in the run directory, the same config) and
# resumes an interrupted one from its last.ckpt (ckpt_path=auto); a script only names the run.
# Needs: BIN (the virtual environment's bin directory); TIMINGS (the stage-time table) for
# timings_begin, stage and timings_end.

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

timings_begin() {  # a fresh stage-time table ($TIMINGS.tmp until timings_end)
    printf '| stage | seconds |\n|---|---|\n' > "$TIMINGS.tmp"
    TIMINGS_START=$(date +%s)
}

stage() {  # stage <name> <command...>: run it between ==>/<== lines and record its wall time
    local name=$1 t0 dt; shift
    t0=$(date +%s)
    echo "==> [$name] $*"
    "$@"
    dt=$(( $(date +%s) - t0 ))
    echo "| $name | $dt |" >> "$TIMINGS.tmp"
    echo "<== [$name] ${dt}s"
}

timings_end() {  # the total row; the table becomes $TIMINGS
    echo "| total | $(( $(date +%s) - TIMINGS_START )) |" >> "$TIMINGS.tmp"
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
