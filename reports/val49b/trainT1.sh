#!/bin/bash
# issue 49, val only: teacher candidate T1 = demo_teacher with the labeled windows from data/demo only (extra_share 0,
# as the students) and lr 2e-3 (the teacher of f3351a3's recipe; 1e-3 was chosen for the fast families' share)
cd /work/main && source .venv/bin/activate
date
denoiser-train experiment=demo_teacher data.extra_share=0.0 model.optimizer.lr=2e-3 seed=0 threads=${THREADS:-1} \
    trainer.enable_progress_bar=false callbacks.progress=null hydra.run.dir=/tmp/s28/val49/teacherT1 > /tmp/s28/val49/teacherT1.log 2>&1
date
