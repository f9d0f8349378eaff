"""Distributed (DDP) correctness on the CPU with 2 gloo processes (docs/scaling.md):

* validation sharded by whole sequences: 2 ranks give the same val PSNR / tPSNR as 1 process on
  the same data and weights, with sequences of uneven length cut in ``val_window`` pieces;

* distillation with ``trainer=ddp`` (2 gloo ranks, ``train.py``): finite losses, the teacher
  frozen, the critic stepped and the same on both ranks, resumable from ``last.ckpt``;

and the distillation critic under ``16-mixed`` (its steps go through Lightning's precision plugin).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from helpers.train_args import NARROW
from hydra import compose, initialize_config_dir

from denoiser.conf import CONF_DIR
from denoiser.configs import instantiate_config
from denoiser.data.synthetic import write_synthetic_sequence

REPO = Path(__file__).resolve().parents[2]
VAL_FRAMES = (5, 3, 6)  # uneven: 2-frame pieces 3 + 2 + 3, and an odd number of sequences for 2 ranks


@pytest.fixture(scope="module")
def uneven_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("uneven")
    for i, frames in enumerate(VAL_FRAMES):
        write_synthetic_sequence(root / "val" / f"seq{i}", frames=frames, width=32, height=32, seed=100 + i)
    write_synthetic_sequence(root / "train" / "seq0", frames=4, width=32, height=32, seed=1)
    return root


def _compose(root: Path, *overrides: str):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("train", overrides=["data=tiny", "net=tiny", "model=teacher", f"data.root={root}",
                                           "output_dir=/tmp/unused", "model.warmup_frames=1", *overrides])


def _validate(cfg, state: dict, devices: int) -> dict:
    from lightning.pytorch.strategies import DDPStrategy

    model = instantiate_config(cfg.model, "model")
    model.load_state_dict(state)
    kwargs = {}
    if devices > 1:
        kwargs["strategy"] = DDPStrategy(start_method="spawn", process_group_backend="gloo")
    trainer = pl.Trainer(accelerator="cpu", devices=devices, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, **kwargs)
    return trainer.validate(model, datamodule=instantiate_config(cfg.data, "data"), verbose=False)[0]


def test_shard_sampler_gives_each_rank_whole_sequences_in_order():
    from denoiser.data.sampler import SequenceShardSampler

    # sequences of 5, 3, 6 frames in 2-frame pieces: (sequence, start, length)
    pieces = [(s, t, min(2, n - t)) for s, n in enumerate(VAL_FRAMES) for t in range(0, n, 2)]
    shards = [list(SequenceShardSampler(pieces, 2, r)) for r in range(2)]
    assert sorted(shards[0] + shards[1]) == list(range(len(pieces)))  # every piece once
    for shard in shards:
        assert shard == sorted(shard)  # in order
    assert {pieces[i][0] for i in shards[0]} == {2} and {pieces[i][0] for i in shards[1]} == {0, 1}  # 6 vs 5+3 frames
    # more ranks than sequences: the idle rank re-runs the shortest sequence (counted once by the gather)
    idle = list(SequenceShardSampler(pieces, 4, 3))
    assert [pieces[i][0] for i in idle] == [1, 1]


def test_combined_sums_count_a_repeated_sequence_once():
    from denoiser.metrics import MetricAccumulator, combine_sequence_sums

    torch.manual_seed(0)
    ref = torch.rand(2, 4, 3, 8, 8)
    out = ref + 0.05 * torch.rand(2, 4, 3, 8, 8)
    one = MetricAccumulator(("psnr", "tpsnr"), warmup=1)
    one.update(out, ref, ["a", "b"])
    a, b = MetricAccumulator(("psnr", "tpsnr"), warmup=1), MetricAccumulator(("psnr", "tpsnr"), warmup=1)
    a.update(out[:1], ref[:1], ["a"])
    b.update(out, ref, ["a", "b"])  # "a" again, as an idle rank's padding
    combined = combine_sequence_sums([a.sequence_sums(), b.sequence_sums()], ["psnr", "tpsnr"])
    for m, v in one.compute().items():
        assert combined[m] == pytest.approx(v, rel=1e-6)


@pytest.mark.slow
def test_two_rank_validation_equals_one_process(uneven_root):
    cfg = _compose(uneven_root, "data.val_window=2")
    torch.manual_seed(0)
    state = instantiate_config(cfg.model, "model").state_dict()
    single = _validate(cfg, state, devices=1)
    whole = _validate(_compose(uneven_root, "data.val_window=null"), state, devices=1)
    double = _validate(cfg, state, devices=2)
    print(f"val/psnr: 1 process {single['val/psnr']:.6f}, 2 ranks {double['val/psnr']:.6f}; "
          f"val/tpsnr: {single['val/tpsnr']:.6f} vs {double['val/tpsnr']:.6f}")
    for key in ("val/psnr", "val/tpsnr", "val/ssim", "val/input_psnr"):
        assert single[key] == pytest.approx(whole[key], abs=1e-4), key  # pieces carry the state
        assert double[key] == pytest.approx(single[key], abs=1e-4), key


QUIET = ["threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
         "trainer.enable_model_summary=false", "trainer.log_every_n_steps=1", "model.image_interval=0"]


@pytest.fixture(scope="module")
def teacher_ckpt(uneven_root, tmp_path_factory) -> Path:
    from denoiser.commands import train as train_script

    out = tmp_path_factory.mktemp("teacher")
    cfg = _compose(uneven_root, *QUIET, f"output_dir={out}", "trainer.max_steps=1", "trainer.val_check_interval=1",
                   "trainer.limit_val_batches=1", "final_validation=false")
    train_script.train(cfg)
    return out / "checkpoints" / "last.ckpt"


def _distill_fit(root: Path, teacher: Path, scale: float, *overrides: str):
    """2 distillation steps under 16-mixed on the CPU (an explicit plugin: Lightning would turn the
    string ``16-mixed`` into ``bf16-mixed`` on a CPU), returning (model, critic before, scaler)."""
    from lightning.pytorch.plugins import MixedPrecision

    cfg = _compose(root, *QUIET, "model=distill", *NARROW, f"model.teacher_ckpt={teacher}",
                   "model.loss.feature_weight=0", "model.loss.adversarial_weight=0.01", *overrides)
    torch.manual_seed(0)
    model = instantiate_config(cfg.model, "model")
    model.configure_model()  # builds the critic now, to compare its weights
    before = {k: v.detach().clone() for k, v in model.critic.named_parameters()}  # not the spectral-norm buffers
    scaler = torch.amp.GradScaler("cpu", init_scale=scale)
    trainer = pl.Trainer(accelerator="cpu", devices=1, max_steps=2, limit_val_batches=0, logger=False,
                         enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                         plugins=[MixedPrecision("16-mixed", "cpu", scaler)])
    trainer.fit(model, datamodule=instantiate_config(cfg.data, "data"))
    assert model.critic_updates == 2 and trainer.global_step == 2  # global_step counts student steps only
    return model, before, scaler


@pytest.mark.slow
def test_critic_steps_under_16_mixed_are_unscaled_and_skip_non_finite_gradients(uneven_root, teacher_ckpt):
    # a scale so large that the float16 gradients overflow: the scaler must skip every step
    model, before, scaler = _distill_fit(uneven_root, teacher_ckpt, 2.0 ** 120)
    after = dict(model.critic.named_parameters())
    assert all(torch.isfinite(v).all() for v in after.values())
    assert all(torch.equal(before[k], after[k]) for k in before), "the critic stepped on non-finite gradients"
    assert scaler.get_scale() < 2.0 ** 120  # the scaler saw the overflow and backed off
    # an ordinary scale: the critic steps, and by the unscaled gradient (SGD: the step is lr x gradient)
    model, before, scaler = _distill_fit(uneven_root, teacher_ckpt, 2.0 ** 16,
                                         "model.critic_optimizer._target_=torch.optim.SGD",
                                         "~model.critic_optimizer.betas", "model.critic_optimizer.lr=1e-3")
    after = dict(model.critic.named_parameters())
    change = max(float((after[k] - before[k]).detach().abs().max()) for k in before)
    assert all(torch.isfinite(v).all() for v in after.values())
    assert 0 < change < 1e-2, change  # about 1.5e-5 here; the scaled gradients (x 65536) moved them by 8.7


class DumpWeights(pl.Callback):
    """Writes ``weights_rank<r>.pt`` (student and critic parameters) into the run directory at the end of training."""

    def on_train_end(self, trainer, pl_module):
        params = {k: v.detach().cpu().clone() for k, v in pl_module.named_parameters() if not k.startswith("teacher.")}
        torch.save(params, Path(trainer.default_root_dir) / f"weights_rank{trainer.global_rank}.pt")


def _train_py(*args: str, cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests"), str(Path(__file__).resolve().parent)])}  # this file: its callbacks
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc.stdout + proc.stderr


@pytest.mark.slow
def test_distillation_on_two_ddp_ranks_trains_freezes_the_teacher_and_resumes(uneven_root, teacher_ckpt, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = tmp_path / "run"
    args = ["data=tiny", "net=tiny", f"data.root={uneven_root}", *QUIET, "model=distill", *NARROW,
            f"model.teacher_ckpt={teacher_ckpt}", "model.loss.adversarial_weight=0.01", f"hydra.run.dir={run_dir}",
            "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true",
            "trainer.benchmark=false", "+trainer.strategy.process_group_backend=gloo", "trainer.val_check_interval=2",
            "trainer.limit_val_batches=2", "callbacks.last.every_n_train_steps=2", "final_validation=false",
            "+callbacks.dump._target_=test_ddp.DumpWeights"]
    out = _train_py(*args, "trainer.max_steps=2", cwd=tmp_path)
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in out
    last = run_dir / "checkpoints" / "last.ckpt"
    first = torch.load(last, map_location="cpu", weights_only=True)
    assert first["global_step"] == 2
    out = _train_py(*args, "trainer.max_steps=4", "ckpt_path=last", cwd=tmp_path)
    assert "Restoring states from the checkpoint" in out or "Restored all states" in out, out[-3000:]
    second = torch.load(last, map_location="cpu", weights_only=True)
    assert second["global_step"] == 4  # continued from step 2 (student steps; critic steps do not count)

    state, state0 = second["state_dict"], first["state_dict"]
    teacher = torch.load(teacher_ckpt, map_location="cpu", weights_only=True)["state_dict"]
    for k, v in teacher.items():  # the teacher stayed frozen
        assert torch.equal(state["teacher." + k[len("net."):]], v), k
    critic = [k for k in state if k.startswith("critic.") and k.endswith("original")]
    assert critic and any(not torch.equal(state[k], state0[k]) for k in critic)  # the critic stepped after the resume
    assert any(not torch.equal(state[k], state0[k]) for k in state if k.startswith("net."))
    ranks = [torch.load(run_dir / f"weights_rank{r}.pt", weights_only=True) for r in range(2)]
    for k, v in ranks[0].items():  # DDP kept the ranks in step: student, adapters and critic alike
        assert torch.allclose(v, ranks[1][k], atol=1e-6), k

    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    losses = [e.value for tag in ("train/loss", "train/critic_loss") for e in acc.Scalars(tag)]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    assert {e.step for e in acc.Scalars("train/loss")} >= {1, 3}  # steps of both runs
