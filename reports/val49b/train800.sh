#!/bin/bash
# issue 49, val only: the shipped teacher, distilled students at 800 steps (the one-stage recipe's 400 doubled)
cd /work/main && source .venv/bin/activate
T=reports/demo/runs/teacher/checkpoints/best.ckpt
run() { denoiser-train experiment=demo_distill model.teacher_ckpt=$T seed=$1 threads=$2 trainer.max_steps=800 \
        trainer.enable_progress_bar=false callbacks.progress=null hydra.run.dir=/tmp/s28/val49/steps800_s$1 > /tmp/s28/val49/steps800_s$1.log 2>&1; }
date; run 0 1 & run 1 1 & wait; date; run 2 2; date
