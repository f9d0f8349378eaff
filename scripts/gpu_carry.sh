#!/usr/bin/env bash
# Prepare .gpu_carry/ (git-ignored), what a lent GPU machine needs besides the working tree
# (docs/gpu.md): the pure-Python wheels it lacks (hydra-core, omegaconf, antlr4-python3-runtime,
# tensorboardX, pytest and its pure dependencies), OpenEXR's wheels for CPython 3.10-3.13, and a
# small subset of data/demo (the first sequences of each split that exists). Checks the total
# stays under CARRY_MIB (default 48 MiB; a run may carry 64 MiB in all).
#   scripts/gpu_carry.sh            # then: the run command of docs/gpu.md
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
DEST=.gpu_carry
CARRY_MIB=${CARRY_MIB:-48}
SEQUENCES=${SEQUENCES:-"train:4 val:1 test:1"}   # split:count of data/demo to carry

version() { "$PY" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$1" 2>/dev/null || true; }
pin() { local v; v=$(version "$1"); if [ -n "$v" ]; then echo "$1==$v"; else echo "$1"; fi; }

rm -rf "$DEST"
mkdir -p "$DEST/wheels" "$DEST/data/demo"
"$PY" -m pip download --quiet --no-deps --only-binary=:all: -d "$DEST/wheels" \
    "$(pin hydra-core)" "$(pin omegaconf)" tensorboardX "$(pin pytest)" "$(pin pluggy)" "$(pin iniconfig)" \
    "$(pin pygments)"
# antlr4-python3-runtime 4.9.x (omegaconf's pin) is an sdist on PyPI: build its pure-Python wheel here
"$PY" -m pip wheel --quiet --no-deps -w "$DEST/wheels" "$(pin antlr4-python3-runtime)"
for py in 3.10 3.11 3.12 3.13; do   # compiled: one wheel per CPython the device may run
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: -d "$DEST/wheels" --python-version "$py" \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux_2_17_x86_64 "$(pin OpenEXR)" 2>/dev/null \
    || "$PY" -m pip download --quiet --no-deps --only-binary=:all: -d "$DEST/wheels" --python-version "$py" \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux_2_17_x86_64 "OpenEXR>=3.2" 2>/dev/null \
    || echo "no OpenEXR wheel for CPython $py"
done
for entry in $SEQUENCES; do
    split=${entry%%:*}; count=${entry##*:}
    [ -d "data/demo/$split" ] || { echo "data/demo/$split: absent, not carried"; continue; }
    mkdir -p "$DEST/data/demo/$split"
    for seq in $(find "data/demo/$split" -mindepth 1 -maxdepth 1 -type d | sort | head -n "$count"); do
        cp -r "$seq" "$DEST/data/demo/$split/"
    done
done
# the commit of the code that travels (the lent machine gets the working tree without .git)
git rev-parse --short HEAD > "$DEST/commit"
[ -z "$(git status --porcelain --untracked-files=no)" ] || sed -i 's/$/-dirty/' "$DEST/commit"
mib=$(du -sm "$DEST" | cut -f1)
echo "$DEST: ${mib} MiB ($(ls "$DEST/wheels" | wc -l) wheels; data: $(cd "$DEST/data/demo" && find . -mindepth 2 -maxdepth 2 -type d | tr '\n' ' '))"
if [ "$mib" -gt "$CARRY_MIB" ]; then
    echo "error: $DEST is ${mib} MiB, over ${CARRY_MIB} MiB: carry fewer sequences (SEQUENCES=...)" >&2
    exit 1
fi
