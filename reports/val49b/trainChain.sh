#!/bin/bash
# issue 49, val only: short fine-tunes of make demo's distilled students, interpolated at alpha 0.5 (RULE_CHAIN.md)
cd /work/main && source .venv/bin/activate
T=reports/demo/runs/teacher/checkpoints/best.ckpt
O=/tmp/s29/val
run() { # name seed share
  n=$1; s=$2; share=$3
  denoiser-train experiment=demo_distill model.teacher_ckpt=$T seed=$s threads=1 \
    model.init_ckpt=reports/demo/runs/student_distilled_s$s/checkpoints/best.ckpt model.param_transfer=null \
    trainer.max_steps=100 model.optimizer.lr=1e-3 callbacks.best=null data.extra_share=$share \
    trainer.enable_progress_bar=false callbacks.progress=null \
    hydra.run.dir=$O/${n}_s$s > $O/${n}_s$s.log 2>&1
  python -m denoiser.commands.interpolate start=reports/demo/runs/student_distilled_s$s/checkpoints/best.ckpt \
    end=$O/${n}_s$s/checkpoints/last.ckpt alpha=0.5 out=$O/${n}_s$s/interpolated_a0.5.ckpt >> $O/${n}_s$s.log 2>&1; }
date
( run C1 0 0.5; run C1 2 0.5; run C2 1 0.0 ) &
( run C1 1 0.5; run C2 0 0.0; run C2 2 0.0 ) &
wait; date
C="{C1_s0: $O/C1_s0/interpolated_a0.5.ckpt, C1_s1: $O/C1_s1/interpolated_a0.5.ckpt, C1_s2: $O/C1_s2/interpolated_a0.5.ckpt, C2_s0: $O/C2_s0/interpolated_a0.5.ckpt, C2_s1: $O/C2_s1/interpolated_a0.5.ckpt, C2_s2: $O/C2_s2/interpolated_a0.5.ckpt}"
denoiser-eval data=demo split=val "ckpt=$C" '~baselines.oidn_balanced' '~baselines.oidn_high' out_dir=$O/evalC_demo > $O/evalC_demo.log 2>&1
denoiser-eval data=demo split=val data.root=data/demo_motion "ckpt=$C" '~baselines.oidn_balanced' '~baselines.oidn_high' out_dir=$O/evalC_motion > $O/evalC_motion.log 2>&1
S=/tmp/s28/val49
python -m denoiser.commands.val_table out=/work/main/reports/val49b/val_table_chain.md reference=one_stage "candidates=[one_stage,refine,steps800,C1,C2]" metric=psnr_f2 "also=[psnr,tpsnr]" \
  "evals={demo: {title: 'data/demo/val', csv: [$S/eval_demo/metrics.csv, $S/eval800_demo/metrics.csv, $O/evalC_demo/metrics.csv]}, motion: {title: 'data/demo_motion/val', csv: [$S/eval_motion/metrics.csv, $S/eval800_motion/metrics.csv, $O/evalC_motion/metrics.csv]}}"
date
