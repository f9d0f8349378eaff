#!/bin/bash
# issue 49, val only: the weight-averaging candidates (RULE_EMA.md) on both vals, then the table
cd /work/main && source .venv/bin/activate
O=/tmp/s29/val
for n in E1_s0 E1_s1 E1_s2 E2_s0 E2_s1 E2_s2; do while [ ! -f $O/$n/DONE ]; do sleep 10; done; done
C="{E1_s0: $O/E1_s0/checkpoints/best.ckpt, E1_s1: $O/E1_s1/checkpoints/best.ckpt, E1_s2: $O/E1_s2/checkpoints/best.ckpt, E2_s0: $O/E2_s0/checkpoints/best.ckpt, E2_s1: $O/E2_s1/checkpoints/best.ckpt, E2_s2: $O/E2_s2/checkpoints/best.ckpt}"
denoiser-eval data=demo split=val "ckpt=$C" '~baselines.oidn_balanced' '~baselines.oidn_high' out_dir=$O/evalEMA_demo > $O/evalEMA_demo.log 2>&1
denoiser-eval data=demo split=val data.root=data/demo_motion "ckpt=$C" '~baselines.oidn_balanced' '~baselines.oidn_high' out_dir=$O/evalEMA_motion > $O/evalEMA_motion.log 2>&1
S=/tmp/s28/val49
python -m denoiser.commands.val_table out=/work/main/reports/val49b/val_table_ema.md reference=one_stage "candidates=[one_stage,refine,E1,E2]" metric=psnr_f2 "also=[psnr,tpsnr]" \
  "evals={demo: {title: 'data/demo/val', csv: [$S/eval_demo/metrics.csv, $O/evalEMA_demo/metrics.csv]}, motion: {title: 'data/demo_motion/val', csv: [$S/eval_motion/metrics.csv, $O/evalEMA_motion/metrics.csv]}}"
date
