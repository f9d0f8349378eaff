#!/usr/bin/env bash
# The device check of a lent GPU (docs/gpu.md): in at most ~8 minutes, the GPU tests, then
# python -m denoiser.commands.tools.gpu_check (inference at 1080p, training steps, a short training run,
# the CPU evaluation of its checkpoint). Results go to $OUT (the run tool brings it back) or
# outputs/gpu_check, and docs/results/gpu.md when run in a checkout.
#   scripts/gpu_check.sh             # make gpu-check
#   RESUME=prev/gpu.md SKIP_TESTS=1 TOTAL_S=230 scripts/gpu_check.sh sections=[train_step,train_run]
#                                    # a second lease: only those sections, the others kept from prev
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-outputs/gpu_check}
mkdir -p "$OUT"
if [ -z "${PY:-}" ]; then
    if [ -x .venv/bin/python ]; then PY=.venv/bin/python; else PY=python3; fi
fi
CARRY=.gpu_carry
if [ -d "$CARRY/wheels" ]; then   # the carried wheels, unpacked for this Python (no index, no pip needed)
    "$PY" - "$CARRY" <<'PYEOF'
import sys, zipfile
from pathlib import Path
carry = Path(sys.argv[1]); site = carry / "site"; site.mkdir(exist_ok=True)
tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
for wheel in sorted((carry / "wheels").glob("*.whl")):
    parts = wheel.name[:-4].split("-")
    if parts[-3] != "py3" and parts[-3] != tag and not parts[-3].startswith("py2.py3"):
        continue  # a compiled wheel of another CPython
    zipfile.ZipFile(wheel).extractall(site)
    print("unpacked", wheel.name)
PYEOF
    export PYTHONPATH="$PWD:$PWD/$CARRY/site${PYTHONPATH:+:$PYTHONPATH}"
    [ -d "$CARRY/data/demo" ] && export DENOISER_DATA="$PWD/$CARRY/data"
else
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONDONTWRITEBYTECODE=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv 2>&1 | tee "$OUT/nvidia-smi.txt"
started=$(date +%s)
extra=("$@")
if [ -n "${RESUME:-}" ]; then cp "$RESUME" "$OUT/gpu.md" && extra+=(keep_report=true); fi
# the GPU tests, and the Triton filter's tests compiled for the GPU
if [ -z "${SKIP_TESTS:-}" ]; then
timeout 150 "$PY" -m pytest -q -p no:cacheprovider -m gpu tests/inference/test_cuda_backend.py tests/lit/test_train_performance.py \
    > "$OUT/pytest_gpu.log" 2>&1; echo "pytest -m gpu: exit $?" | tee -a "$OUT/pytest_gpu.log"
timeout 90 "$PY" -m pytest -q -p no:cacheprovider tests/inference/test_triton_filter.py \
    > "$OUT/pytest_triton.log" 2>&1; echo "pytest triton: exit $?" | tee -a "$OUT/pytest_triton.log"
tail -n 3 "$OUT/pytest_gpu.log" "$OUT/pytest_triton.log"
fi
left=$(( ${TOTAL_S:-460} - ($(date +%s) - started) ))
budget=$(( left - 60 > 60 ? left - 60 : 60 ))
timeout $(( left > 90 ? left : 90 )) "$PY" -m denoiser.commands.tools.gpu_check out="$OUT" budget_s="$budget" "${extra[@]}" 2>&1 \
    | tee "$OUT/gpu_check.log" | grep -v "^\s*$" | tail -n 60
[ -z "${SKIP_TESTS:-}" ] && {
    echo; echo "## Tests"; echo
    echo '```'; tail -n 3 "$OUT/pytest_gpu.log"; tail -n 3 "$OUT/pytest_triton.log"; echo '```'
} >> "$OUT/gpu.md"
# keep what comes back small: the last checkpoint only (the one evaluated)
find "$OUT/train/checkpoints" -name '*.ckpt' ! -name last.ckpt -delete 2>/dev/null
mkdir -p docs/results && cp "$OUT/gpu.md" docs/results/gpu.md
# the run tool brings back at most 8 files, 2 folders down: the report, its rows and the logs stay
# loose, the training run, its evaluation and the smaller logs go into one archive
extras=$(cd "$OUT" && ls -d train eval train.log nvidia-smi.txt 2>/dev/null)
[ -n "$extras" ] && (cd "$OUT" && tar czf runs.tar.gz $extras && rm -rf $extras)
echo "report: $OUT/gpu.md; $(find "$OUT" -type f | wc -l) files in $OUT"
