"""End-to-end training runs on a tiny synthetic dataset: teacher, student (crash + resume),
distillation with every term and with ablations, a Hydra multirun over three ablations, and a
user error. Every run writes real checkpoints and TensorBoard event files that are read back."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from denoiser.checkpoint import load_denoiser
from denoiser.conf import CONF_DIR
from denoiser.configs import instantiate_config
from denoiser.data.synthetic import write_synthetic_sequence

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from helpers.train_args import FAST, NARROW

from denoiser.commands import train as train_script


class CrashAtStep(pl.Callback):
    """Raises RuntimeError once ``global_step`` reaches ``step`` (a simulated crash)."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, *args, **kwargs):
        if trainer.global_step >= self.step:
            raise RuntimeError("simulated crash")


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tinydata")
    for split, count, labeled in (("train", 2, True), ("val", 1, True), ("unlabeled", 1, False)):
        for i in range(count):
            write_synthetic_sequence(root / split / f"seq{i}", frames=4, width=32, height=32, labeled=labeled,
                                     seed=10 * i + len(split))
    return root


def run(data_root: Path, out: Path, *overrides: str) -> dict:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[*FAST, f"data.root={data_root}", f"output_dir={out}", *overrides])
    return train_script.train(cfg)


def events(log_dir: Path) -> EventAccumulator:
    acc = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    acc.Reload()
    return acc


def event_files(log_dir: Path) -> list[Path]:
    return sorted(log_dir.glob("events.out.tfevents.*"), key=os.path.getmtime)


@pytest.fixture(scope="module")
def teacher_run(data_root, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("teacher")
    metrics = run(data_root, out, "model=teacher")
    assert {"val/psnr", "val/ssim", "val/tpsnr"} <= set(metrics)
    return out


def test_teacher_run_writes_checkpoints_and_tensorboard(teacher_run):
    ckpt = torch.load(teacher_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 4
    # model=teacher selected kernel=teacher (5, 7, 9) for the tiny widths given on the command line
    assert ckpt["hyper_parameters"]["net"]["filter"]["kernel_sizes"] == [5, 7, 9]
    assert ckpt["hyper_parameters"]["net"]["unet"]["encoder"] == [8, 12, 16]
    net = load_denoiser(teacher_run / "checkpoints" / "last.ckpt")
    assert sum(p.numel() for p in net.parameters()) > 0
    assert (teacher_run / "checkpoints" / "best.ckpt").is_file()

    acc = events(teacher_run / "tb")
    scalars = set(acc.Tags()["scalars"])
    assert {"train/loss", "train/loss_smape", "train/loss_gradient", "train/loss_temporal",
            "val/psnr", "val/ssim", "val/tpsnr", "val/input_psnr"} <= scalars
    assert any(t.startswith("lr-") for t in scalars)  # LearningRateMonitor
    psnr = [e.value for e in acc.Scalars("val/psnr")]
    assert len(psnr) == 2 and all(10 < v < 100 for v in psnr)
    images = set(acc.Tags()["images"])
    assert {"train/panel", "val/panel"} <= images
    panel = acc.Images("val/panel")[0]
    assert panel.width == 3 * panel.height  # noisy | output | reference, whole 32x32 frames
    # hyperparameters logged together with the final metrics (TensorBoard HPARAMS plugin)
    assert "_hparams_/experiment" in acc.Tags()["tensors"] or "_hparams_/experiment" in str(acc.summary_metadata)
    assert "final/psnr" in scalars and abs(acc.Scalars("final/psnr")[-1].value - psnr[-1]) < 1e-3


def test_student_resumes_after_a_crash_from_the_saved_step(data_root, tmp_path):
    crash = ["+callbacks.crash._target_=test_train_runs.CrashAtStep", "+callbacks.crash.step=3",
             "trainer.max_steps=6"]
    with pytest.raises(RuntimeError, match="simulated crash"):
        run(data_root, tmp_path, "model=student", *crash)
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 2
    first_file = event_files(tmp_path / "tb")[-1]

    run(data_root, tmp_path, "model=student", "trainer.max_steps=6", "ckpt_path=last")
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 6
    resumed = [f for f in event_files(tmp_path / "tb") if f != first_file and f.stat().st_mtime >= first_file.stat().st_mtime]
    steps = sorted({e.step for f in resumed for e in _scalars(f, "train/loss")})
    assert steps and steps[0] >= 2 and steps[-1] <= 6  # the resumed run started at the saved step, not 0


def _scalars(path: Path, tag: str):
    acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
    acc.Reload()
    return acc.Scalars(tag) if tag in acc.Tags()["scalars"] else []


def test_resume_from_a_missing_checkpoint_is_a_config_error(data_root, tmp_path):
    from denoiser.errors import ConfigError

    with pytest.raises(ConfigError, match="ckpt_path=last"):
        run(data_root, tmp_path, "ckpt_path=last")


def _teacher_and_student_state(out: Path):
    return torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)


def test_distillation_with_every_term(data_root, teacher_run, tmp_path):
    teacher_ckpt = teacher_run / "checkpoints" / "last.ckpt"
    run(data_root, tmp_path, "model=distill", *NARROW, f"model.teacher_ckpt={teacher_ckpt}",
        "data.use_unlabeled=true", "model.loss.feature_weight=0.1", "model.loss.adversarial_weight=0.01")
    scalars = set(events(tmp_path / "tb").Tags()["scalars"])
    for term in ("kd_smape", "kd_gradient", "kd_temporal", "gt_smape", "gt_gradient", "gt_temporal",
                 "feature", "adversarial"):
        assert f"train/loss_{term}" in scalars, term
    assert "train/critic_loss" in scalars
    ckpt = _teacher_and_student_state(tmp_path)
    assert ckpt["global_step"] == 4  # student steps only; critic steps do not count
    assert len(ckpt["optimizer_states"]) == 2
    state = ckpt["state_dict"]
    assert any(k.startswith("critic.") for k in state) and any(k.startswith("adapters.") for k in state)
    # the teacher stayed frozen: its weights in the distillation checkpoint equal the teacher checkpoint's
    teacher_state = torch.load(teacher_ckpt, map_location="cpu", weights_only=True)["state_dict"]
    for k, v in teacher_state.items():
        assert torch.equal(state["teacher." + k[len("net."):]], v), k
    student = load_denoiser(tmp_path / "checkpoints" / "last.ckpt")
    assert student.unet.feature_channels == [8, 4, 6]  # the narrow student, not the teacher


def test_distillation_ablations_really_remove_their_terms(data_root, teacher_run, tmp_path):
    teacher_ckpt = teacher_run / "checkpoints" / "last.ckpt"
    run(data_root, tmp_path / "noadv", "model=distill", *NARROW, f"model.teacher_ckpt={teacher_ckpt}",
        "ablation=no_adversarial")
    scalars = set(events(tmp_path / "noadv" / "tb").Tags()["scalars"])
    assert "train/loss_kd_smape" in scalars and "train/loss_gt_smape" in scalars
    assert "train/loss_adversarial" not in scalars and "train/critic_loss" not in scalars
    ckpt = _teacher_and_student_state(tmp_path / "noadv")
    assert len(ckpt["optimizer_states"]) == 1  # no critic optimizer, so no critic step
    assert not any(k.startswith("critic.") for k in ckpt["state_dict"])

    run(data_root, tmp_path / "nokd", "model=distill", *NARROW, f"model.teacher_ckpt={teacher_ckpt}",
        "ablation=no_kd")
    scalars = set(events(tmp_path / "nokd" / "tb").Tags()["scalars"])
    assert {"train/loss_gt_smape", "train/loss_gt_temporal"} <= scalars
    assert not {s for s in scalars if s.startswith("train/loss_kd") or s in (
        "train/loss_feature", "train/loss_adversarial", "train/critic_loss")}
    state = _teacher_and_student_state(tmp_path / "nokd")["state_dict"]
    assert not any(k.startswith(("teacher.", "critic.", "adapters.")) for k in state)


def test_multirun_over_three_ablations(data_root, tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, str(REPO / "train.py"), "-m", *FAST, f"data.root={data_root}", "model=student",
           "trainer.max_steps=2", "trainer.val_check_interval=2", "ablation=none,no_pyramid,no_temporal",
           f"hydra.sweep.dir={sweep}"]
    proc = subprocess.run(cmd, check=False, cwd=REPO, capture_output=True, text=True, timeout=400,
                          env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and (p / "tb").is_dir())
    assert [j.name.split("_", 1)[0] for j in jobs] == ["0", "1", "2"]
    filters = set()
    for job in jobs:
        acc = events(job / "tb")
        assert {"train/loss", "val/psnr"} <= set(acc.Tags()["scalars"]), job
        assert {"train/panel", "val/panel"} <= set(acc.Tags()["images"]), job
        ckpt = torch.load(job / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        net = ckpt["hyper_parameters"]["net"]
        filters.add((net["filter"]["_target_"], net["temporal"] is None))
    assert filters == {("denoiser.nn.pyramid.PyramidFilter", False), ("denoiser.nn.filters.SingleKernelFilter", False),
                       ("denoiser.nn.pyramid.PyramidFilter", True)}


def test_distillation_without_teacher_is_a_one_line_error(data_root, tmp_path, capsys):
    """What `python train.py model=distill` (no teacher) prints: one line, exit code 2, no traceback."""
    from denoiser.commands.app import guarded

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[*FAST, f"data.root={data_root}", f"output_dir={tmp_path}", "model=distill"])
    with pytest.raises(SystemExit) as exit_info:
        guarded(train_script.train)(cfg)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: model.teacher_ckpt") and "Traceback" not in err[0]


def test_validation_carries_the_state_across_sequence_pieces(data_root, teacher_run):
    """Whole validation sequences and the same sequences in 2-frame pieces give the same metrics."""
    results = []
    for window in ("null", "2"):
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=[*FAST, f"data.root={data_root}", "output_dir=/tmp/unused",
                                              "model=teacher", f"data.val_window={window}"])
        model = instantiate_config(cfg.model, "model")
        state = torch.load(teacher_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        model.load_state_dict(state["state_dict"])
        trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False)
        results.append(trainer.validate(model, datamodule=instantiate_config(cfg.data, "data"), verbose=False)[0])
    assert results[0]["val/psnr"] == pytest.approx(results[1]["val/psnr"], abs=1e-4)
    assert results[0]["val/tpsnr"] == pytest.approx(results[1]["val/tpsnr"], abs=1e-4)
