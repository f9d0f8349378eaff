"""make release's pipeline (conf/pipeline/release.yaml, issue 62): its stages and command lines, the
script stage in another interpreter, the seed shipped chosen on val, the experiments' joined data."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from denoiser.configs import compose_config
from denoiser.errors import ConfigError
from denoiser.pipeline.runner import Context, argv_of
from denoiser.pipeline.stages import Job, best_on_val, check_stage

VENV_BIN = Path(sys.executable).parent


def test_the_dry_run_lists_every_stage_with_the_release_recipe(tmp_path):
    out = subprocess.run([str(VENV_BIN / "denoiser-pipeline"), "pipeline=release", "dry_run=true",
                          f"blender_python={sys.executable}", f"report={tmp_path / 'r'}"],
                         capture_output=True, text=True, check=True).stdout
    stages = [line.split("]", 1)[0].lstrip("[") for line in out.splitlines() if line.startswith("[")]
    assert list(dict.fromkeys(stages)) == ["render", "render_cycles", "teacher", "students", "val", "bench", "ship"]
    assert "render_set=release_hires" in out and "experiment=release_teacher" in out
    assert f"{sys.executable} scripts/blender_sequences.py --root data/release_cycles --split unlabeled --set release" in out
    assert out.count("experiment=release_distill") == 3 and "+experiment=release_data split=val" in out


def test_a_script_stage_runs_in_its_own_interpreter():
    stage = {"script": "scripts/x.py", "python": "/opt/bpy/bin/python", "args": ["--a", "1"]}
    check_stage("s", stage)
    assert argv_of(stage, Job("s", {}, ["--a", "1"]), Context(), None) == ["/opt/bpy/bin/python", "scripts/x.py", "--a", "1"]
    with pytest.raises(ConfigError, match="exactly one of command, module, script or copy"):
        check_stage("s", {"script": "x.py", "module": "m"})


def test_the_seed_shipped_is_the_best_on_val(tmp_path):
    path = tmp_path / "metrics.csv"
    rows = [("teacher", "mean", 35.0), ("student_s0", "a", 40.0), ("student_s0", "mean", 31.0),
            ("student_s1", "mean", 31.5), ("student_s2", "mean", 30.9), ("OIDN-fast", "mean", 33.0)]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "scene", "sequence", "psnr"])
        w.writerows([(m, s, s, v) for m, s, v in rows])
    assert best_on_val(path, tmp_path / "runs", "student_s") == str(tmp_path / "runs" / "student_s1" / "checkpoints" / "last.ckpt")
    with pytest.raises(ConfigError, match="no method named pupil"):
        best_on_val(path, tmp_path / "runs", "pupil")


@pytest.mark.parametrize("experiment", ["release_teacher", "release_distill"])
def test_the_release_experiments_join_every_root_of_the_release(experiment):
    cfg = compose_config([f"experiment={experiment}"], "train")
    roots = [r if isinstance(r, str) else dict(r) for r in cfg.data.extra_roots]
    assert cfg.data.root.endswith("data/release") and roots[:2] == [cfg.data.root + "_motion", cfg.data.root + "_hires"]
    assert roots[2] == {"root": cfg.data.root + "_cycles", "layout": "blender"} and cfg.data.extra_share is None
    assert cfg.data.use_unlabeled is (experiment == "release_distill")


def test_make_demo_distils_from_the_release_teacher_without_its_teacher_stage(tmp_path):
    def dry(*args):
        return subprocess.run([str(VENV_BIN / "denoiser-pipeline"), "pipeline=demo", "dry_run=true", *args],
                              capture_output=True, text=True, check=True).stdout

    own, release = dry(), dry("teacher=release")
    assert any(line.startswith("[teacher]") for line in own.splitlines()) and "model.teacher_ckpt=reports/demo/runs/teacher/checkpoints/" in own
    assert not any(line.startswith("[teacher]") for line in release.splitlines()) and "==> [teacher] skipped" in release
    students = [line for line in release.splitlines() if line.startswith("[students]") and "demo_distill" in line]
    assert len(students) == 3 and all("model.teacher_ckpt=release:teacher" in s and "reports/demo_release/runs/" in s
                                      for s in students)
    assert "teacher: release:teacher" in next(line for line in release.splitlines() if line.startswith("[eval]"))
