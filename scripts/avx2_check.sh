#!/usr/bin/env bash
# Issue 66's done criteria, measured in one go on the first AVX2-only CPU a session gets (AVX2 and
# no AVX-512; an AVX-512 CPU is refused: there, docs/export.md says how to see an AVX2 profile).
#
#   bash scripts/avx2_check.sh [OUT=reports/avx2_check]     # after `make setup`; about 25 minutes
#   bash scripts/avx2_check.sh --variants DIR               # only write the variant sources (stage 4)
#
# Stages (each skips what it finds done in OUT, so a stopped run resumes):
#   1. frames: $DENOISER_DATA's demo/test if it has one, else one 8-frame cornell sequence rendered
#      into OUT/data (denoiser-render, the frames every round of the issue used);
#   2. the issue's bench line, repeats=15 (OUT/bench): the f32 student against OIDN-fast, paired per
#      round, and its share of the fp32 peak; then its row in docs/results/cpu_speed.csv (.md);
#   3. the same line with profile=true repeats=3 (OUT/profile): Reference's share of node time and
#      each extension operation's milliseconds;
#   4. the choices made for AVX2 on an AVX-512 machine's x86-64-v3 build, paired on this CPU by
#      scripts/ovext_op_bench.cpp (16 pairs, 1 and 2 threads): EmbedNet's 8 outputs at a time
#      against 4 (1e20475) and the head-0 product's 8 skip channels at a time against all 16
#      (44164a6); B / A below 1 means the variant is faster than the shipped code;
#   5. OUT/summary.md from the files above, the figures the issue asks for beside its bounds.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
EXT=denoiser/inference/ovext

variants() {  # DIR: copies of the extension with one choice each undone; fails if a choice moved
    local dir=$1
    rm -rf "$dir" && mkdir -p "$dir/q4" "$dir/g16"
    cp "$EXT"/*.hpp "$EXT"/extension.cpp "$dir/q4/" && cp "$EXT"/*.hpp "$EXT"/extension.cpp "$dir/g16/"
    sed -i 's/constexpr int Q = NOUT % 8 == 0 \&\& S < 16 ? 8 : /constexpr int Q = /' "$dir/q4/embed_net.hpp"
    sed -i 's/constexpr int64_t G = S < 16 \&\& NC % 8 == 0 ? 8 : NC;/constexpr int64_t G = NC;/' \
        "$dir/g16/pyramid_filter_head.hpp"
    if cmp -s "$EXT/embed_net.hpp" "$dir/q4/embed_net.hpp" || cmp -s "$EXT/pyramid_filter_head.hpp" \
        "$dir/g16/pyramid_filter_head.hpp"; then
        echo "avx2_check: the lines of EmbedNet's Q or the head-0 product's G changed; update variants() in $0" >&2
        exit 2
    fi
}

if [ "${1:-}" = "--variants" ]; then
    variants "${2:?--variants DIR}"
    exit 0
fi

flags=" $(grep -m1 '^flags' /proc/cpuinfo | cut -d: -f2) "
if [[ $flags != *" avx2 "* ]]; then
    echo "avx2_check: this CPU has no AVX2 ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2))" >&2
    exit 2
fi
if [[ $flags == *" avx512f "* ]]; then
    echo "avx2_check: this CPU has AVX-512, the check is for an AVX2-only CPU (here: docs/export.md, 'An AVX2 CPU's profile on an AVX-512 machine')" >&2
    exit 2
fi
OUT=$(realpath -m "${1:-reports/avx2_check}")
BIN=$ROOT/.venv/bin
mkdir -p "$OUT"
for v in ONEDNN_MAX_CPU_ISA DNNL_MAX_CPU_ISA MKL_ENABLE_INSTRUCTIONS DENOISER_OVEXT_MARCH; do unset "$v"; done
echo "avx2_check: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) cores, into $OUT"

# 1. frames
DATA=${DENOISER_DATA:-}
if [ -z "$DATA" ] || [ ! -d "$DATA/demo/test" ]; then
    DATA=$OUT/data
    if [ ! -f "$DATA/demo/test/cornell_000/frame_0007.exr" ]; then
        echo "[1/5] rendering one 8-frame cornell sequence into $DATA"
        DENOISER_DATA=$DATA "$BIN/denoiser-render" scene=cornell split=test name=demo sequences=1 frames=8 spp=4 \
            ref_spp=64 aux=samples hydra.run.dir="$OUT/render"
    fi
fi
echo "[1/5] frames: $DATA/demo/test"

bench() {  # NAME ARGS...: the issue's bench line into OUT/NAME (skipped when its report exists)
    local name=$1
    shift
    if [ -f "$OUT/$name/bench.json" ]; then
        echo "  $name: done before ($OUT/$name/report.md)"
        return
    fi
    DENOISER_DATA=$DATA "$BIN/denoiser-bench" data=demo 'variants={student:{net:demo_student,kernel:student}}' \
        'sizes=[[1080,1920]]' threads=2 'use_backends=[openvino_f32]' quality=false '~baselines.oidn_balanced' \
        '~baselines.oidn_high' "$@" hydra.run.dir="$OUT/$name.tmp" && rm -rf "$OUT/$name" && mv "$OUT/$name.tmp" "$OUT/$name"
}
echo "[2/5] the bench line, repeats=15"
bench bench repeats=15
"$BIN/python" -m denoiser.report.cpu_speed add "$OUT/bench/bench.json"
echo "[3/5] the bench line, profile=true repeats=3"
bench profile repeats=3 profile=true

echo "[4/5] the AVX2 choices, paired on this CPU"
OV=$("$BIN/python" -c 'import openvino, os; print(os.path.dirname(openvino.__file__))')
variants "$OUT/variants"
for v in q4 g16; do
    op=$([ $v = q4 ] && echo EmbedNet || echo "PyramidFilterHead FactoredHead")
    if [ ! -s "$OUT/pair_$v.txt" ]; then
        g++ -O3 -fno-math-errno -std=c++17 -march=native -I"$OV/include" scripts/ovext_op_bench.cpp \
            -DEXT_SOURCE="\"$ROOT/$EXT/extension.cpp\"" -DEXT_B="\"$OUT/variants/$v/extension.cpp\"" \
            "$OV"/libs/libopenvino.so.* "$OV"/libs/libopenvino_onnx_frontend.so.* "$OV"/libs/libtbb.so.12 \
            -Wl,-rpath,"$OV/libs" -o "$OUT/pair_$v"
        { "$OUT/pair_$v" 1 16 "$op"; "$OUT/pair_$v" 2 16 "$op"; } > "$OUT/pair_$v.tmp"
        mv "$OUT/pair_$v.tmp" "$OUT/pair_$v.txt"
    fi
    echo "  $v ($op):" && sed 's/^/    /' "$OUT/pair_$v.txt"
done

echo "[5/5] $OUT/summary.md"
"$BIN/python" - "$OUT" <<'EOF'
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
bench, prof = (json.loads((out / n / "bench.json").read_text()) for n in ("bench", "profile"))
m = bench["machine"]
s = next(r for r in bench["speedups"] if r["dtype"] == "fp32")
row = next(r for r in bench["rows"] if f"{r['method']} ({r['backend']})" == s["student"])
p = next(r for r in prof["rows"] if r.get("profile"))
node = sum(p["profile"].values())
share = p["profile"].get("Reference", 0.0) / node
ext = ", ".join(f"{k} {v:.1f}" for k, v in p.get("extension_profile", {}).items())
lines = [f"# Issue 66 on {m['cpu']} ({m['cpu_id']}), commit {m['commit']}, {m['date']}", "",
         "| criterion | bound | measured | met (the ratio: its whole interval) |", "|---|---:|---:|---:|",
         f"| f32 student vs OIDN-fast, 1080p, 2 threads (paired, repeats={bench['repeats']}) | >= 2x | "
         f"{s['ratio']:.2f}x ({s['ratio_lo']:.2f}-{s['ratio_hi']:.2f}); {s['student_ms']:.1f} vs {s['baseline_ms']:.1f} ms | "
         f"{'yes' if s['ratio_lo'] >= 2 else 'no'} |",
         f"| share of the fp32 peak ({m['matmul_peak_gflops']:.1f} GFLOP/s) | >= 65% | {100 * row['peak_fraction']:.1f}% | "
         f"{'yes' if row['peak_fraction'] >= 0.65 else 'no'} |",
         f"| Reference in node time (profile, last step of repeats=3) | <= 15% | {100 * share:.1f}% of {node:.0f} ms | "
         f"{'yes' if share <= 0.15 else 'no'} |", "",
         f"The extension's operations, ms: {ext}.", "",
         "Kernels that ran: " + "; ".join(f"{k} {', '.join(v)}" for k, v in p.get("kernels", {}).get("openvino", {}).items()
                                         if k in ("Convolution", "MatMul", "Subgraph"))
         + f"; the extension built for {p.get('kernels', {}).get('extension')}.", "",
         "The AVX2 choices (B: the variant, A: the shipped code; B / A below 1: the variant is faster):", ""]
for v, what in (("q4", "EmbedNet, 4 outputs at a time"), ("g16", "head-0 product, all 16 skip channels at a time")):
    lines += [f"- {what}:", "", "```", (out / f"pair_{v}.txt").read_text().strip(), "```", ""]
(out / "summary.md").write_text("\n".join(lines))
print("\n".join(lines[:8]))
EOF
