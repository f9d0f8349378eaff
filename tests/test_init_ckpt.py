"""Fine-tuning: ``model.init_ckpt`` starts supervised training, or distillation, from a checkpoint's weights."""

import pytest
import torch
from conftest import compose_command, tiny_checkpoint

from denoiser.checkpoint import load_weights, read_checkpoint
from denoiser.configs import compose_net_config
from denoiser.errors import ConfigError, UserError
from denoiser.lit.distill import DistillationModule
from denoiser.lit.supervised import SupervisedModule

LOSS = {"_target_": "denoiser.lit.losses.DenoiseLoss"}
OPTIMIZER = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-3}


def module(init_ckpt=None, net="tiny"):
    torch.manual_seed(123)  # the random draw the checkpoint's weights must replace
    return SupervisedModule(net=compose_net_config(net, "student"), loss=LOSS, optimizer=OPTIMIZER, init_ckpt=init_ckpt)


def test_init_ckpt_loads_every_weight(tmp_path):
    path = tiny_checkpoint(tmp_path / "start.ckpt", seed=7)
    saved = {k.removeprefix("net."): v for k, v in read_checkpoint(path)["state_dict"].items()}
    tuned, fresh = module(str(path)).net.state_dict(), module().net.state_dict()
    assert set(tuned) == set(saved)
    assert all(torch.equal(tuned[k], saved[k]) for k in saved)
    assert any(not torch.equal(fresh[k], saved[k]) for k in saved)  # without it: the seed's own draw
    assert module(str(path)).hparams["init_ckpt"] == str(path)


def test_another_architecture_is_one_error_naming_the_file(tmp_path):
    path = tiny_checkpoint(tmp_path / "tiny.ckpt")
    other = SupervisedModule(net=compose_net_config("demo_student", "student"), loss=LOSS, optimizer=OPTIMIZER).net
    with pytest.raises(UserError, match=r"tiny\.ckpt: its weights do not fit the network being trained"):
        load_weights(other, path)
    with pytest.raises(UserError, match=r"missing\.ckpt: checkpoint file does not exist"):
        load_weights(other, tmp_path / "missing.ckpt")  # the missing file is named, not a traceback


def test_demo_motion_tune_composes_the_teacher_recipe_with_a_start(tmp_path):
    cfg = compose_command("train", ["experiment=demo_motion_tune", "model.init_ckpt=t.ckpt"])
    teacher = compose_command("train", ["experiment=demo_motion_teacher"])
    assert cfg.model.init_ckpt == "t.ckpt" and teacher.model.init_ckpt is None
    assert cfg.trainer.max_steps == 400 and cfg.model.optimizer.lr == 5e-4
    assert cfg.net == teacher.net and cfg.data == teacher.data  # the motion recipe's data, the teacher's network


def student(tmp_path, init_ckpt=None, **kw):
    torch.manual_seed(123)
    teacher = tiny_checkpoint(tmp_path / "teacher.ckpt", seed=3)
    return DistillationModule(net=compose_net_config("tiny", "student"), optimizer=OPTIMIZER,
                              teacher_ckpt=str(teacher), init_ckpt=init_ckpt, **kw)


def test_distillation_starts_from_init_ckpt_not_from_the_teacher(tmp_path):
    path = tiny_checkpoint(tmp_path / "student.ckpt", seed=7)
    saved = {k.removeprefix("net."): v for k, v in read_checkpoint(path)["state_dict"].items()}
    tuned, fresh = student(tmp_path, str(path)).net.state_dict(), student(tmp_path).net.state_dict()
    assert all(torch.equal(tuned[k], saved[k]) for k in saved)
    assert any(not torch.equal(fresh[k], saved[k]) for k in saved)
    assert student(tmp_path, str(path)).hparams["init_ckpt"] == str(path)


def test_distillation_refuses_init_ckpt_with_param_transfer(tmp_path):
    path = tiny_checkpoint(tmp_path / "student.ckpt", seed=7)
    transfer = {"_target_": "denoiser.lit.transfer.L1ChannelTransfer", "probe_size": 8}
    with pytest.raises(ConfigError, match=r"model.init_ckpt and model.param_transfer: give one"):
        student(tmp_path, str(path), param_transfer=transfer)


def test_demo_motion_distill_tune_composes_the_student_recipe_with_a_start():
    cfg = compose_command("train", ["experiment=demo_motion_distill_tune", "model.init_ckpt=s.ckpt",
                                    "model.teacher_ckpt=t.ckpt"])
    recipe = compose_command("train", ["experiment=demo_motion_distill", "model.teacher_ckpt=t.ckpt"])
    assert cfg.model.init_ckpt == "s.ckpt" and recipe.model.init_ckpt is None
    assert cfg.model.param_transfer is None and recipe.model.param_transfer is not None
    assert cfg.trainer.max_steps == 400 and cfg.model.optimizer.lr == 5e-4
    assert cfg.net == recipe.net and cfg.data == recipe.data and cfg.model.loss == recipe.model.loss
    assert cfg.callbacks.best is None and recipe.callbacks.best is not None  # evaluated at last.ckpt
    no_kd = compose_command("train", ["experiment=demo_motion_nokd_tune", "model.init_ckpt=s.ckpt"])
    assert no_kd.model.init_ckpt == "s.ckpt" and no_kd.trainer.max_steps == 400 and no_kd.callbacks.best is None
    assert no_kd.data == compose_command("train", ["experiment=demo_motion"]).data
