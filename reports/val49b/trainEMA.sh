#!/bin/bash
# issue 49, val only: make demo's one-stage distilled students with EMA weight averaging (RULE_EMA.md)
cd /work/main && source .venv/bin/activate
T=reports/demo/runs/teacher/checkpoints/best.ckpt
O=/tmp/s29/val
run() { # name seed extra...
  n=$1; s=$2; shift 2
  denoiser-train experiment=demo_distill model.teacher_ckpt=$T seed=$s threads=1 \
    trainer.enable_progress_bar=false callbacks.progress=null \
    +callbacks.ema._target_=lightning.pytorch.callbacks.EMAWeightAveraging "$@" \
    hydra.run.dir=$O/${n}_s$s > $O/${n}_s$s.log 2>&1; }
E1="+callbacks.ema.decay=0.98"
E2="+callbacks.ema.decay=0.99 +callbacks.ema.update_starting_at_step=200"
date
( run E1 0 $E1; run E1 2 $E1; run E2 1 $E2 ) &
( run E1 1 $E1; run E2 0 $E2; run E2 2 $E2 ) &
wait; date
