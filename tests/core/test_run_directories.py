"""Scripts lean on the trainer: a run directory is a checkpoint for every loader (best, else
last), and ``skip_done`` skips a finished run of the same config, whatever the spelling of its
overrides (the pipeline scripts no longer keep their own DONE logic)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.checkpoints import tiny_checkpoint

from denoiser.checkpoint import checkpoint_paths, load_denoiser, resolve_checkpoint
from denoiser.errors import UserError

REPO = Path(__file__).resolve().parents[2]


def test_a_run_directory_loads_its_best_checkpoint_else_its_last(tmp_path):
    run = tmp_path / "runs" / "student_s0"
    tiny_checkpoint(run / "checkpoints" / "last.ckpt", seed=1)
    assert resolve_checkpoint(run) == run / "checkpoints" / "last.ckpt"
    last = load_denoiser(run)
    tiny_checkpoint(run / "checkpoints" / "best.ckpt", seed=2)
    assert resolve_checkpoint(run) == run / "checkpoints" / "best.ckpt"
    best = load_denoiser(run)
    want = load_denoiser(run / "checkpoints" / "best.ckpt")
    for a, b in zip(best.state_dict().values(), want.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert any(not torch.equal(a, b) for a, b in zip(best.state_dict().values(), last.state_dict().values(),
                                                     strict=True))
    file = run / "checkpoints" / "best.ckpt"
    assert resolve_checkpoint(file) == file   # a file is itself


def test_a_directory_without_checkpoints_is_one_line_naming_it(tmp_path):
    (tmp_path / "empty" / "checkpoints").mkdir(parents=True)
    with pytest.raises(UserError) as err:
        load_denoiser(tmp_path / "empty")
    message = str(err.value)
    assert message.startswith(str(tmp_path / "empty")) and "\n" not in message
    assert "checkpoints/best.ckpt or checkpoints/last.ckpt" in message
    with pytest.raises(UserError, match="does not exist"):
        resolve_checkpoint(tmp_path / "missing")


def test_two_runs_best_checkpoints_are_named_by_their_runs(tmp_path):
    a, b = (tmp_path / r / "checkpoints" / "best.ckpt" for r in ("teacher", "student_s0"))
    assert list(checkpoint_paths([str(a), str(b)])) == ["teacher/best", "student_s0/best"]
    assert list(checkpoint_paths([str(tmp_path / "teacher"), str(tmp_path / "student_s0")])) == \
        ["teacher", "student_s0"]


def test_denoiser_export_takes_a_run_directory(tmp_path):
    """The command line: denoiser-export ckpt=<run dir> writes the ONNX file beside the run's best checkpoint."""
    pytest.importorskip("onnx")
    run = tmp_path / "run"
    tiny_checkpoint(run / "checkpoints" / "best.ckpt")
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.export", f"ckpt={run}", "trace_size=[32,32]",
                           "check_size=[48,64]"], cwd=tmp_path, capture_output=True, text=True, check=False,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (run / "checkpoints" / "best.onnx").stat().st_size > 1000


def _finished(run: Path, overrides: list[str]) -> None:
    run.mkdir(parents=True)
    (run / "metrics.json").write_text(json.dumps({"overrides": overrides, "metrics": {"val/psnr": 30.5}}))
    (run / "DONE").touch()


def _train(run: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "denoiser.commands.train", *overrides, "skip_done=true",
                           "ckpt_path=auto", f"hydra.run.dir={run}"], cwd=run.parent, capture_output=True, text=True,
                          check=False, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300)


RECIPE = ["experiment=demo_distill", "model.teacher_ckpt=t.ckpt"]


def test_skip_done_skips_the_same_config_however_it_was_asked_for(tmp_path):
    # make demo's students were trained with ablation=history_clamp before the clamp became the
    # recipe's own value, and with another thread count: the same run, skipped
    run = tmp_path / "student_distilled_s0"
    _finished(run, [*RECIPE, "ablation=history_clamp", "seed=0", "threads=1"])
    proc = _train(run, *RECIPE, "seed=0", "threads=2", "trainer.enable_progress_bar=false")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "finished before, skipped (skip_done=true)" in proc.stderr
    # another seed, or a change of the recipe, is another run: one line, exit 1
    for other in (["seed=1"], ["seed=0", "ablation=no_unlabeled"], ["seed=0", "net.temporal.history_clamp=2.0"]):
        proc = _train(run, *RECIPE, *other)
        assert proc.returncode != 0 and "holds a finished run of other overrides" in proc.stderr, other
        assert "Traceback" not in proc.stderr
