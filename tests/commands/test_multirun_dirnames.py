"""A multirun's job folders are named from their overrides (conf/train.yaml's hydra.sweep.subdir,
denoiser.configs.job_dirname): a tiny sweep over the learning rate through Hydra's basic launcher."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from denoiser.configs import MAX_DIRNAME, job_dirname
from denoiser.data.synthetic import write_synthetic_sequence

REPO = Path(__file__).resolve().parents[2]


def test_unsafe_characters_become_one_underscore_and_a_long_name_is_cut_with_a_hash():
    assert job_dirname("ablation=k3,model.optimizer.lr=0.001") == "ablation=k3,model.optimizer.lr=0.001"
    assert job_dirname("data.crop=[32, 32],note='a b/c'") == "data.crop=_32,_32_,note=_a_b_c"
    assert job_dirname("") == "defaults"
    a, b = (job_dirname("x" * 200 + tail) for tail in ("1", "2"))
    assert len(a) == len(b) == MAX_DIRNAME and a != b and a[:40] == b[:40]


@pytest.mark.slow
def test_a_sweep_over_two_learning_rates_names_its_folders_by_the_values(tmp_path):
    root = tmp_path / "data"
    for split in ("train", "val"):
        write_synthetic_sequence(root / split / "seq0", frames=4, width=32, height=32, labeled=True, seed=len(split))
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, str(REPO / "train.py"), "-m", "data=tiny", "net=tiny", "model=student", "debug=fast_dev_run",
           "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null", f"data.root={root}",
           "model.optimizer.lr=0.001,0.002", f"hydra.sweep.dir={sweep}"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=400, check=False,
                          env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and (p / ".hydra").is_dir())
    assert jobs == ["0_data=tiny,debug=fast_dev_run,model.optimizer.lr=0.001,model=student,net=tiny",
                    "1_data=tiny,debug=fast_dev_run,model.optimizer.lr=0.002,model=student,net=tiny"], jobs
