#!/bin/bash
# issue 49, val only: the one-stage distilled students (400 steps) under the refine recipe's fine-tuned teacher (f3351a3)
cd /work/main && source .venv/bin/activate
T=/tmp/f335/reports/demo_refine/runs/teacher_tuned/checkpoints/best.ckpt
run() { denoiser-train experiment=demo_distill model.teacher_ckpt=$T seed=$1 threads=$2 \
        trainer.enable_progress_bar=false callbacks.progress=null hydra.run.dir=/tmp/s28/val49/tuned_teacher_s$1 > /tmp/s28/val49/tuned_teacher_s$1.log 2>&1; }
date; run 0 1 & run 1 1 & wait; date; run 2 2; date
